"""The Neural-ESO method: pure math, no I/O, no bus."""
