"""Process support: console output, the status panel, systemd notify, tickers, the device thread, ptys,
SIGTERM handled like Ctrl-C.

Imports only :mod:`racecar_hw.base`; the drivers (timers, fake ptys) and everything above use it.
"""
