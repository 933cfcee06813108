"""skeleton.png: the skeleton drawn over the point cloud at a few frames, bones coloured,
the subject that was kept coloured over the grey scene it was cut from."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def draw_skeleton_png(path, observed: list, registered: np.ndarray, labels: np.ndarray,
                      joint_positions: np.ndarray, parents: np.ndarray, stamps, n_panels: int = 4,
                      scene: list | None = None) -> Path:
    """Camera view (x right, y down) of `n_panels` frames spread over the sequence.

    scene: per-frame (S_t, 3) whole views (light grey, optional); observed: per-frame
    (N_t, 3) subject points kept by the segmentation (blue-grey); registered: (F, M, 3)
    coloured by bone label; joint_positions: (F, J, 3) drawn as dots joined along `parents`.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    n_frames = len(registered)
    picks = np.unique(np.linspace(0, n_frames - 1, min(n_panels, n_frames)).astype(int))
    fig, axes = plt.subplots(1, len(picks), figsize=(4.2 * len(picks), 5.2), squeeze=False)
    colours = plt.get_cmap('tab20')(np.arange(max(labels.max() + 1, 1)) % 20)
    for ax, f in zip(axes[0], picks):
        if scene is not None and len(scene[f]):
            ax.scatter(scene[f][:, 0], scene[f][:, 1], s=0.3, c='0.85', linewidths=0)
        cloud = observed[f]
        if len(cloud):
            ax.scatter(cloud[:, 0], cloud[:, 1], s=0.5, c='#7f9fbf', linewidths=0)
        ax.scatter(registered[f, :, 0], registered[f, :, 1], s=1.2, c=colours[labels], linewidths=0)
        joints = joint_positions[f]
        for child, parent in enumerate(parents):
            if parent >= 0:
                ax.plot(joints[[child, parent], 0], joints[[child, parent], 1], '-', c='k', lw=2)
        ax.scatter(joints[:, 0], joints[:, 1], s=28, c='red', edgecolors='k', zorder=3)
        ax.set_title(f'frame {f}  t = {stamps[f]:.2f} s')
        if len(cloud):
            # frame the subject; the scene around it may extend metres further
            low, high = cloud[:, :2].min(axis=0), cloud[:, :2].max(axis=0)
            pad = 0.5 * (high - low).max()
            ax.set_xlim(low[0] - pad, high[0] + pad)
            ax.set_ylim(low[1] - pad, high[1] + pad)
        ax.set_aspect('equal')
        ax.invert_yaxis()
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
    fig.suptitle(f'{len(parents)} joints, {labels.max() + 1} bones')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
