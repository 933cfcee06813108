"""A captured mesh sequence (same topology every frame, exact vertex motion) as an
AnimatedBody without bones: registration ground truth only."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .animated import AnimatedBody, SkinnedSurface


class MeshSequenceError(ValueError):
    """A mesh sequence that cannot be used; the message is one line naming the file."""


def load_mesh_sequence(path, frames: int | None = None, start: int = 0,
                       facing: tuple = (1.0, 0.0, 0.0)) -> AnimatedBody:
    """Frames [start, start + frames) of an .npz with `vertices` (F, V, 3) metres y up,
    `faces` (T, 3) and `fps`, turned so the performer faces +z (it faces `facing` in the
    file; the samba performer of Vlasic et al. faces +x), feet on y = 0, centred over the
    origin at the first frame."""
    path = Path(path)
    if not path.is_file():
        raise MeshSequenceError(f'{path}: mesh sequence does not exist')
    try:
        data = np.load(path, allow_pickle=False)
        vertices, faces, fps = data['vertices'], data['faces'], float(data['fps'])
    except KeyError as error:
        raise MeshSequenceError(f'{path}: needs arrays vertices (F x V x 3), faces (T x 3) and fps; '
                                f'missing {error}') from None
    except (OSError, ValueError) as error:
        raise MeshSequenceError(f'{path}: cannot read: {error}') from None
    if vertices.ndim != 3 or vertices.shape[2] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshSequenceError(f'{path}: vertices must be F x V x 3 and faces T x 3, got '
                                f'{vertices.shape} and {faces.shape}')
    if not 0 <= start < len(vertices):
        raise MeshSequenceError(f'{path}: start frame {start} outside 0..{len(vertices) - 1}')
    stop = len(vertices) if frames is None else min(len(vertices), start + frames)
    vertices = vertices[start:stop].astype(np.float64)
    # turn about y so `facing` becomes +z
    angle = np.arctan2(facing[0], facing[2])
    c, s = np.cos(-angle), np.sin(-angle)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    vertices = vertices @ turn.T
    first = vertices[0]
    vertices -= np.array([first[:, 0].mean(), first[:, 1].min(), first[:, 2].mean()])
    n_frames = len(vertices)
    return AnimatedBody(path.stem, np.zeros((n_frames, 0, 4, 4)), [], np.zeros(0, dtype=np.int64), [],
                        np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                        skin=SkinnedSurface(vertices, np.asarray(faces, dtype=np.int64),
                                            np.full(vertices.shape[1], -1)),
                        frame_time=1.0 / fps, description=f'captured mesh sequence {path.name}')
