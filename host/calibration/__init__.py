"""Calibration: camera intrinsics from chessboards, M_cr and track placement by hand-eye."""

from host.calibration.handeye import HandEyeResult, HandEyeView, calibrate_handeye
from host.calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics, find_chessboard

__all__ = [
    "HandEyeResult",
    "HandEyeView",
    "IntrinsicsResult",
    "calibrate_handeye",
    "calibrate_intrinsics",
    "find_chessboard",
]
