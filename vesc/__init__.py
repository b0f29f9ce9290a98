"""The VESC motor controller: sans-I/O codec, serial driver, fake VESC, Ackermann conversion, odometry."""
