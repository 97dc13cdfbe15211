"""Real messages of the loop's topics as payloads, for benches that must match the pipeline's sizes."""
from __future__ import annotations

import struct

from runtime.schema import EstimateMsg, SetpointMsg, StateMsg


def payload(topic: str, stamp_s: float = 0.0) -> bytes:
    """``stamp_s`` as 8 bytes (float64) in place of the first 8 bytes of a real ``topic`` message: exactly the
    size the pipeline sends, with a stamp a forwarder can carry without decoding."""
    msg = {
        "state": StateMsg(seq=12345, stamp_s=stamp_s, t_s=12.34, pos_enu_m=(0.1, 0.2, 1.0), vel_enu_mps=(0.01, 0.02, 0.03),
                          roll_rad=0.01, pitch_rad=0.02, yaw_rad=0.03, source="sim"),
        "estimate": EstimateMsg(seq=12345, stamp_s=stamp_s, t_s=12.34, f_hat_mps2=(0.1, 0.2, -0.3),
                                f_n_mps2=(0.0, 0.0, -0.25), delta_f_hat_mps2=(0.1, 0.2, -0.05),
                                z=(1.0, 0.1, 0.01, 0.02), pathway="neural_eso", network_id="base@L1.492",
                                warm_ticks=12345),
        "setpoint": SetpointMsg(seq=12345, stamp_s=stamp_s, state_stamp_s=stamp_s, t_s=12.34, roll_rad=0.01,
                                pitch_rad=0.02, yaw_rad=0.03, thrust_norm=0.52, thrust_n=10.3,
                                acc_cmd_enu_mps2=(0.1, 0.2, 0.3), estimate_source="estimator"),
    }[topic]
    return struct.pack("<d", stamp_s) + msg.to_bytes()[8:]
