"""The step objects of the flight loop: pure, clock-free, no bus (services/ wraps each in a process)."""
