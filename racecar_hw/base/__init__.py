"""The ground floor: messages, the bus, clocks, parameters, errors, links and transforms.

Every other package of racecar-hw (``vesc``, ``lidar_drivers``, ``mux``, ``safety`` and the rest of
``racecar_hw``) may import from here; nothing here imports from any of them.
"""
