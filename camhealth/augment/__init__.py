"""Kornia-style corruption modules that simulate a camera (thesis Fig. 3.7).

>>> import torch
>>> from camhealth.augment import CameraCorruption
>>> cam = CameraCorruption()                       # defocus, motion, all noise sources, random cameras
>>> y = cam(torch.rand(8, 1, 128, 128))            # corrupted batch, same shape, in [0, 1]
>>> labels = cam.labels()                          # mtf (8, 16), sigma_dn (8, 3), metadata, ...
"""

from camhealth.augment.blur import RandomDefocusBlur, RandomMotionBlur, motion_kernel_size
from camhealth.augment.camera import CameraCorruption
from camhealth.augment.sensor_noise import RandomSensorNoise

__all__ = ["CameraCorruption", "RandomDefocusBlur", "RandomMotionBlur", "RandomSensorNoise", "motion_kernel_size"]
