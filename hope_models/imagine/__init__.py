"""Imagination from a learned world model: the mid_loop's action-conditioned heads, a CEM planner in
them, and the episodes it writes (`imagine --method model`). Never imports the simulator
(hope_models.sim, dm_control, mujoco): on a robot there is none (tests/test_imagine_model.py)."""
