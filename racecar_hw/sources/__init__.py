"""Built-in command and topic sources: the set-point relay, the figure-8 driver, scan summaries."""
