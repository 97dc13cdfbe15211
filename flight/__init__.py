"""The step objects of the flight loop: pure, clock-free, no bus (services/ wraps each in a process)."""

KEEP_SAMPLES = 64  # how far back (samples) a step object keeps messages waiting for their partner of the same seq


def forget_older(by_seq: dict, seq: int) -> None:
    """Drop the entries more than :data:`KEEP_SAMPLES` before ``seq``, once there are twice as many
    (a scan per sample would cost more than the rest of the sample's bookkeeping)."""
    if len(by_seq) > 2 * KEEP_SAMPLES:
        for old in [s for s in by_seq if s < seq - KEEP_SAMPLES]:
            del by_seq[old]
