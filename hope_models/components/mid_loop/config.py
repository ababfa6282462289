"""The Mid Loop's configuration, apart from its model so that it imports no torch."""
from __future__ import annotations

from dataclasses import dataclass

from hope_models.components.ssm_config import SSMConfig, check_timescales


@dataclass
class MidLoopConfig:
    act_dim: int = 0
    n_codes: int = 0  # codebook size of the frozen VQ-VAE
    horizon_steps: tuple[int, ...] = (5, 10)  # grid steps ahead, one prediction head each
    d_model: int = 128
    n_layers: int = 2
    d_state: int = 64
    mlp_ratio: int = 2
    min_timescale: float = 1.0  # grid steps (100 ms each in the default window)
    max_timescale: float = 64.0
    dropout: float = 0.1  # on the SSM's input and the head's: a few dozen episodes overfit without it
    # The action-conditioned world model (mid_loop.py, "World model"): from the context at a grid
    # point, the exact observation there and the actions held over the next wm_horizon grid steps,
    # the observation after each of them. 0 = none. Over a grid frame VQ-VAE: the joints (grid_world_model).
    wm_horizon: int = 4
    wm_hidden: int = 128
    wm_weight: float = 1.0  # of its MSE (normalised units) beside the codes' NLL in the loss
    # A grid frame tokenizer (VQ-VAE layout "grid": one code per cell from one shared codebook) is
    # read and predicted per cell by grid_model.py; these fields are read by that model only.
    obs_dim: int = 0  # the joints (the dataset's observation vector): an input and a target; from the data
    keypoints: int = 8  # where things are: learned keypoints over the cells (code_keypoints.py), at every point
    cell_rank: int = 32  # width of the shared per-cell decoder: logits = u_cell @ V^T, V [n_codes, rank]
    score_points: int = 2  # code targets scored per window and horizon: the anchor's and the last in-window ones
    # training decodes every cell whose code changed and this fraction of the others (weighted back):
    # most cells of a frame hold still, and their logits would be most of a step's cost
    stay_sample: float = 0.25
    # each cell's predicted distribution is (1 - copy_mix) x the decoder's + copy_mix x copy-last's
    # (grid_metrics.py): on held-out episodes the decoder alone is sure of changes that do not come
    copy_mix: float = 0.2
    joint_weight: float = 1.0  # of the joints' MSE (normalised units) beside the codes' NLL per cell
    # the grid Mid Loop's world model (wm_* heads, wm_horizon steps): the joints after each held action,
    # what `imagine --method model` plans in on a camera robot; 1 = it has one, 0 = none (the grid
    # checkpoints made before it: mid_loop's stored_defaults)
    grid_world_model: int = 1

    def ssm_config(self) -> SSMConfig:
        return SSMConfig(self.d_model, self.d_state, self.n_layers, self.mlp_ratio, self.min_timescale,
                         self.max_timescale)

    def validate(self) -> None:
        if self.act_dim < 1 or self.n_codes < 2:
            raise ValueError(f"act_dim={self.act_dim} must be >= 1 and n_codes={self.n_codes} >= 2")
        if not self.horizon_steps or any(int(s) != s or s < 1 for s in self.horizon_steps):
            raise ValueError(f"horizon_steps={self.horizon_steps} must be positive whole grid steps")
        if self.d_model < 1 or self.n_layers < 1 or self.d_state < 1 or self.mlp_ratio < 1:
            raise ValueError("d_model, n_layers, d_state and mlp_ratio must be >= 1")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout={self.dropout} must be within [0, 1)")
        if self.wm_horizon < 0 or self.wm_hidden < 1 or not self.wm_weight >= 0:
            raise ValueError(f"wm_horizon={self.wm_horizon} must be >= 0, wm_hidden={self.wm_hidden} >= 1 and "
                             f"wm_weight={self.wm_weight} >= 0")
        if self.obs_dim < 0 or self.keypoints < 1 or self.cell_rank < 1 or self.score_points < 1:
            raise ValueError(f"obs_dim={self.obs_dim} must be >= 0, keypoints={self.keypoints}, cell_rank="
                             f"{self.cell_rank} and score_points={self.score_points} >= 1")
        if not self.joint_weight >= 0 or not 0.0 < self.stay_sample <= 1.0 or not 0.0 <= self.copy_mix < 1.0:
            raise ValueError(f"joint_weight={self.joint_weight} must be >= 0, stay_sample={self.stay_sample} "
                             f"within (0, 1] and copy_mix={self.copy_mix} within [0, 1)")
        if self.grid_world_model not in (0, 1):
            raise ValueError(f"grid_world_model={self.grid_world_model} must be 1 (a world model over the joints) or 0")
        check_timescales(self.min_timescale, self.max_timescale)
