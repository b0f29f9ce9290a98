"""Network interfaces: the topic table they share, and the live servers (Zenoh, Foxglove, web).

Everything here sends off the control path: bus callbacks hand messages to bounded drop-oldest
queues served by other threads or tasks, and work is skipped while nobody listens.
"""
