"""Torch's compiler (torch._dynamo, sympy: ~1.5 s of CPU and ~70 MB of RSS a process here) stays
unloaded where nothing compiles: a training job (hope_models/train/adamw.py, the deterministic flag
in train/job_setup.py) and a process that loads checkpoints of every kind of model
(components/meta_init.py: the meta-device check of components/build.py runs no arithmetic)."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

TRAIN_JOB = textwrap.dedent("""
    import sys, torch
    from hope_models.data.synthetic import generate_dataset
    from hope_models.train.loop import TrainConfig, train
    root = sys.argv[1]
    generate_dataset(root + "/ds", 600, obs_dim=6, act_dim=2, seed=1, episode_seconds=(5, 8))
    r = train(TrainConfig(component="fast_loop", data=root + "/ds", run_dir=root + "/run", steps=3, seed=0,
                          batch_size=8, threads=1, checkpoint_every_steps=3, cache_dir=root + "/cache",
                          thermal_zone=None, vcgencmd=None))
    assert r.outcome == "completed", r.message
    print(torch.are_deterministic_algorithms_enabled(), "torch._dynamo" in sys.modules)
""")

LOAD_EVERY_KIND = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import torch
    from safetensors.torch import save_file
    from hope_models.components.build import build_component, component_from_checkpoint
    from hope_models.data.cache import load_or_build
    from hope_models.data.synthetic import generate_dataset

    root = Path(sys.argv[1])
    def save(comp, name):
        d = root / name
        d.mkdir()
        if hasattr(comp.model, "initialized"):
            comp.model.initialized.fill_(1)  # a VQ-VAE is read only once its codebook is (here: as built)
        save_file(comp.model.state_dict(), str(d / "model.safetensors"))
        (d / "config.json").write_text(json.dumps(comp.config()))
        return d
    def spec(name, **kw):
        generate_dataset(root / name, 400, obs_dim=4, act_dim=2, seed=4, episode_seconds=(10, 20), **kw)
        return load_or_build(root / name, root / (name + "-cache"))[0].spec
    vec, cam = spec("vector"), spec("frames", frame_blobs=True)
    torch.manual_seed(0)
    dirs = [save(build_component("vqvae", vec), "vq")]
    dirs += [save(build_component(c, vec, vqvae_dir=dirs[0]), c) for c in ("fast_loop", "mid_loop")]
    dirs += [save(build_component("vqvae", cam), "frame-vq")]
    grid = save(build_component("vqvae", cam, model_config={"layout": "grid", "patch": 8, "n_codes": 16,
                                                             "channels": 4}), "grid-vq")
    dirs += [grid] + [save(build_component(c, cam, vqvae_dir=grid), "grid-" + c) for c in ("fast_loop", "mid_loop")]
    before = "torch._dynamo" in sys.modules
    loaded = [type(component_from_checkpoint(d).model).__name__ for d in dirs]
    print(json.dumps({"loaded": loaded, "before": before, "after": "torch._dynamo" in sys.modules}))
""")


def _run(script: str, tmp_path: Path) -> str:
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, cwd=REPO,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout.strip().splitlines()[-1]


def test_a_training_job_leaves_torchs_compiler_unloaded(tmp_path):
    """Still computing with torch's deterministic kernels."""
    assert _run(TRAIN_JOB, tmp_path).split() == ["True", "False"]


def test_loading_a_checkpoint_of_any_kind_of_model_leaves_torchs_compiler_unloaded(tmp_path):
    out = json.loads(_run(LOAD_EVERY_KIND, tmp_path))
    assert out["loaded"] == ["VQVAE", "FastLoop", "MidLoop", "VQVAE", "VQVAE", "FastLoop", "GridMidLoop"], out
    assert out == {**out, "before": False, "after": False}, out
