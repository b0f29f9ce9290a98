"""Process support: console output, the status panel, link states, stop signals, systemd notify,
tickers, the device thread, ptys.

Imports only :mod:`racecar_hw.base`; the drivers (timers, fake ptys) and everything above use it.
"""
