"""The step objects of the flight loop: pure, clock-free, no bus (services/ wraps each in a process)."""

KEEP_SAMPLES = 64  # how far back (samples) a step object keeps messages waiting for their partner of the same seq
