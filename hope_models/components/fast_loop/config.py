"""The Fast Loop's configuration, apart from its model so that it imports no torch."""
from __future__ import annotations

from dataclasses import dataclass

from hope_models.components.ssm_config import check_timescales

KEYPOINT_READERS = ("policy", "frames")  # code_keypoints.READERS, without torch
DRAWINGS = ("vectors", "codes")  # code_keypoints.DRAWINGS


@dataclass
class FastLoopConfig:
    obs_dim: int = 0
    act_dim: int = 0
    window_k: int = 5  # grid points the policy sees: the training window's K (set from the window spec)
    d_model: int = 128
    d_state: int = 256  # one SSM layer, so a wide state
    mlp_ratio: int = 2  # encoder / head gated MLP hidden width = mlp_ratio * d_model
    min_timescale: float = 1.0  # grid steps (20 ms each in the default window)
    max_timescale: float = 16.0
    n_codes: int = 0  # codebook size of the frozen VQ-VAE whose codes are inputs; 0 = none
    keypoints: int = 16  # a grid VQ-VAE's codes are read as this many learned keypoints (code_keypoints.py)
    # "frames": the keypoints learn where things are by drawing the codes back (self-supervised),
    # the policy reads them without gradient; "policy": behaviour cloning alone places them
    keypoint_reader: str = "frames"
    render_weight: float = 1.0  # the drawing loss beside the action's MSE (keypoint_reader "frames")
    # what a "frames" reader's points draw back: each cell's code vector ("vectors", MSE) or its
    # code as one of n_codes classes ("codes", cross-entropy: ~30x the work a step)
    keypoint_draw: str = "vectors"
    # The observation's first joint angle (set from the feature spec: -1 when it has none): the
    # keypoints are also read turned into that joint's frame, where a reach is the same wherever
    # the target stands around the robot. Its mean and std undo the observation's normalisation.
    view_joint: int = -1
    view_joint_mean: float = 0.0
    view_joint_std: float = 1.0

    def validate(self) -> None:
        if self.obs_dim < 1 or self.act_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} and act_dim={self.act_dim} must be >= 1")
        if self.window_k < 1:
            raise ValueError(f"window_k={self.window_k} must be >= 1")
        if self.d_model < 1 or self.d_state < 1 or self.mlp_ratio < 1:
            raise ValueError("d_model, d_state and mlp_ratio must be >= 1")
        if self.keypoints < 1:
            raise ValueError(f"keypoints={self.keypoints} must be >= 1")
        if self.keypoint_reader not in KEYPOINT_READERS:
            raise ValueError(f"keypoint_reader={self.keypoint_reader!r} must be one of {', '.join(KEYPOINT_READERS)}")
        if self.keypoint_draw not in DRAWINGS:
            raise ValueError(f"keypoint_draw={self.keypoint_draw!r} must be one of {', '.join(DRAWINGS)}")
        if not self.render_weight >= 0:
            raise ValueError(f"render_weight={self.render_weight} must be >= 0")
        if not -1 <= self.view_joint < self.obs_dim:
            raise ValueError(f"view_joint={self.view_joint} must be -1 (none) or an observation index < {self.obs_dim}")
        if not self.view_joint_std > 0:
            raise ValueError(f"view_joint_std={self.view_joint_std} must be > 0")
        check_timescales(self.min_timescale, self.max_timescale)
