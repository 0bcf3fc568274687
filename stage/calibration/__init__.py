"""Calibration: each sensor's transform into stage space, and keeping it right.

- ``pairs``/``streams``: skeletons seen at the same moment by two sensors,
  time alignment (lag search), copied-stream detection.
- ``methods``: rigid (closed form, default), regression and ga (the
  K-Multiscope paper's), ga3d, trajectory (seed 002), floor (seed 004).
- ``fitness``: the one documented fitness formula.
- ``graph``/``offline``: many sensors, best paths, chains, joint refinement.
- ``healing``: live calibration and self-healing on a running engine.
- ``cli``: ``stage calibrate``. See docs/calibration.md.
"""

from .fitness import SIGMA_M, Evaluation, evaluate_points, fitness_from_mse
from .healing import LiveCalibrator, LiveEvent, attach_live
from .live import LiveSettings
from .methods import METHODS, CalibrationResult, calibrate
from .offline import RigCalibration, SensorCalibration, calibrate_streams
from .pairs import PairSet, find_lag, pair_streams
from .streams import Stream, find_identical_streams, load_recording, streams_from_datagrams

__all__ = ["SIGMA_M", "Evaluation", "evaluate_points", "fitness_from_mse", "LiveCalibrator",
           "LiveEvent", "attach_live", "LiveSettings", "METHODS", "CalibrationResult",
           "calibrate", "RigCalibration", "SensorCalibration", "calibrate_streams",
           "PairSet", "find_lag", "pair_streams", "Stream",
           "find_identical_streams", "load_recording", "streams_from_datagrams"]
