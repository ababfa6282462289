"""The reflex's simulator: the dm_control reacher (reach and track tasks), its expert, the RLDS
recorder and closed-loop evaluation (docs/reflex.md).

Importing this package does not import dm_control; reacher.make_env does, after setting MUJOCO_GL
("disabled", or "egl" when frames are asked for; a value already in the environment wins).
"""
