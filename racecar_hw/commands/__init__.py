"""One module per ``racecar-hw`` command; each provides ``register(subparsers)``."""
