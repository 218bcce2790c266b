"""A worked AutoPower plug-in: a frame-difference motion detector and the camera that feeds it.

`GreyCamera` (the source, on the robot) renders small greyscale frames of a bright square moving
over a noisy background; `MotionDetector` (the component, wherever the planner puts it) compares
each frame with the previous one. The previous frame is its state, so moving it mid-run must
carry that frame along, byte for byte.
"""

from motion_demo.camera import GreyCamera
from motion_demo.motion import MotionDetector

__all__ = ["GreyCamera", "MotionDetector"]
