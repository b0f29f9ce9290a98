"""The priority Ackermann command mux: inputs, locks, e-stop, rate limiter."""
