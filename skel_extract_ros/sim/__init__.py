"""Synthetic articulated subjects seen by a virtual depth camera, with ground truth."""
from .camera import DepthCamera, Intrinsics, NoiseModel
from .sequence import FRAME_ID, SimulatedSequence, generate_sequence
from .subjects import SUBJECTS, Subject, make_subject

__all__ = ['DepthCamera', 'Intrinsics', 'NoiseModel', 'FRAME_ID', 'SimulatedSequence',
           'generate_sequence', 'SUBJECTS', 'Subject', 'make_subject']
