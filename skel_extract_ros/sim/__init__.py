"""Synthetic and real-motion articulated subjects seen by a virtual depth camera, with
ground truth: built-in subjects (sequence.py), motion capture, rigs and mesh sequences
(sources.py), all through one renderer (render.py) and scene builder (scenes.py)."""
from .camera import DepthCamera, Intrinsics, NoiseModel
from .render import FRAME_ID, SimulatedSequence
from .scenes import SCENES
from .sequence import generate_sequence
from .subjects import SUBJECTS, Subject, make_subject

__all__ = ['DepthCamera', 'Intrinsics', 'NoiseModel', 'FRAME_ID', 'SimulatedSequence', 'SCENES',
           'generate_sequence', 'SUBJECTS', 'Subject', 'make_subject']
