"""The gate's baselines check (hope_models/promote/baselines.py): a vqvae or mid_loop that does not
beat its trivial baselines on held-out episodes is refused with the figures; `--force` still
promotes it. Real checkpoints: 12 sim reacher demos of 200 steps, a VQ-VAE trained for 300 steps
and a Mid Loop trained for 20 (deliberately undertrained)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

import run_trainer
from hope_models.components.mid_loop.held_out import mid_loop_verdict
from hope_models.components.vqvae.held_out import vqvae_verdict
from hope_models.promote.gate import gate_candidate
from hope_models.promoted import read_pointer
from hope_models.settings import load_settings
from hope_models.train.loop import TrainConfig, train

ENV = {"HOPE_GATE_REFLEX_EPISODES": "2"}


def _train(root: Path, component: str, steps: int, **kw) -> Path:
    result = train(TrainConfig(component=component, data=str(root / "demos"), run_dir=str(root / "runs" / component),
                               steps=steps, batch_size=32, threads=1, cache_dir=str(root / "cache"),
                               thermal_zone=None, vcgencmd=None, log_every=50, checkpoint_every_steps=10_000, **kw))
    assert result.outcome == "completed", result.message
    return Path(result.checkpoint)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    import torch

    from hope_models.sim.recorder import record_dataset

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("baselines")
    ENV["HOPE_DATA_ROOTS"] = str(root)
    record_dataset(root / "demos", 12, task="reach", noise=1.0, steps=200)
    vq = _train(root, "vqvae", 300)
    mid = _train(root, "mid_loop", 20, vqvae_dir=str(vq))
    yield {"root": root, "vqvae": vq, "mid_loop": mid}
    ENV.pop("HOPE_DATA_ROOTS")
    torch.set_num_threads(threads)


def _settings(**env):
    return load_settings("/nonexistent-home-for-gate-tests", env={**ENV, **env})


def test_an_undertrained_mid_loop_is_refused_with_the_baseline_figures(models):
    r = gate_candidate(models["mid_loop"], None, settings=_settings())
    assert r.passed is False
    check = next(c for c in r.checks if c["check"] == "baselines")
    assert check["status"] == "failed"
    text = r.reasons[0]
    for label in ("0.5s", "1s"):  # each horizon with its figures against both baselines
        assert f"{label}: nll " in text and "copy-last" in text and "code frequency" in text
    assert "observation error" in text and "needs 30% lower" in text
    val = r.metrics["candidate_val"]
    assert val["copy_last_obs_mse_0.5s"] > 0 and val["code_freq_nll_1s"] > 0
    # the figures in the verdict are those the run itself reported on the same held-out batches
    reported = json.loads((models["mid_loop"].parent.parent / "result.json").read_text())["summary"]["val"]
    assert reported["nll_0.5s"] == pytest.approx(val["nll_0.5s"], rel=1e-6)


def test_the_vqvae_verdict_names_the_variance_kept_and_follows_the_setting(models):
    strict = gate_candidate(models["vqvae"], None, settings=_settings(HOPE_GATE_VQVAE_MAX_NMSE="0.0001"))
    nmse = strict.metrics["candidate_val"]["recon_nmse"]
    assert strict.passed is False and 0 < nmse < 1
    assert f"keeps {1 - nmse:.1%} of the variance" in strict.reasons[0] and "limit 0.0001" in strict.reasons[0]
    loose = gate_candidate(models["vqvae"], None, settings=_settings(HOPE_GATE_VQVAE_MAX_NMSE="0.99"))
    assert next(c for c in loose.checks if c["check"] == "baselines")["status"] == "passed"


def test_force_still_promotes_a_refused_mid_loop(models, tmp_path, monkeypatch, capsys):
    home = tmp_path / "home"
    monkeypatch.setenv("HOPE_HOME", str(home))
    for k, v in ENV.items():
        monkeypatch.setenv(k, v)
    assert run_trainer.main(["promote", "--checkpoint", str(models["mid_loop"]), "--json"]) == 1
    assert read_pointer(home, "mid_loop") is None
    assert run_trainer.main(["promote", "--checkpoint", str(models["mid_loop"]), "--force", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["promoted"] is True and out["forced"] is True
    assert read_pointer(home, "mid_loop")["checkpoint"] == str(models["mid_loop"].resolve())


# -- the verdicts on plain figures ----------------------------------------------------------------

def _mid_val(**over):
    val = {}
    for label in ("0.5s", "1s"):
        val.update({f"nll_{label}": 10.8, f"copy_last_nll_{label}": 14.2, f"code_freq_nll_{label}": 14.5,
                    f"obs_mse_{label}": 0.5, f"copy_last_obs_mse_{label}": 0.9})
    val.update(over)
    return val


def test_mid_loop_verdict_needs_every_horizon_to_beat_every_baseline():
    assert mid_loop_verdict(_mid_val(), ["0.5s", "1s"], True, 0.3)[0] == "passed"
    status, text = mid_loop_verdict(_mid_val(**{"obs_mse_1s": 0.7}), ["0.5s", "1s"], True, 0.3)  # 22% lower
    assert status == "failed" and "1s: its predicted observation's error is 22% lower than copy-last's" in text
    status, text = mid_loop_verdict(_mid_val(**{"nll_0.5s": 14.3}), ["0.5s", "1s"], True, 0.3)  # beats freq only
    assert status == "failed" and "0.5s: its code log-likelihood does not beat both baselines" in text
    # frames: no observation error to compare, the log-likelihoods decide
    assert mid_loop_verdict(_mid_val(**{"obs_mse_1s": 5.0}), ["0.5s", "1s"], False, 0.3)[0] == "passed"
    status, text = mid_loop_verdict({}, ["0.5s"], True, 0.3)
    assert status == "failed" and "not measured" in text
    # the world model (wm_ heads) must beat copy-last too
    status, text = mid_loop_verdict(_mid_val(wm_obs_mse=0.39, wm_copy_obs_mse=0.86), ["0.5s", "1s"], True, 0.3)
    assert status == "passed" and "world model: observation error 0.3900 vs copy-last 0.8600" in text
    status, text = mid_loop_verdict(_mid_val(wm_obs_mse=0.9, wm_copy_obs_mse=0.86), ["0.5s", "1s"], True, 0.3)
    assert status == "failed" and text.endswith("its world model predicts no better than copy-last")


def test_vqvae_verdict_vectors_and_frames():
    assert vqvae_verdict({"recon_nmse": 0.04, "perplexity": 36, "code_usage": 1.0}, False, 0.05)[0] == "passed"
    status, text = vqvae_verdict({"recon_nmse": 0.2, "perplexity": 36, "code_usage": 1.0}, False, 0.05)
    assert status == "failed" and "keeps 80.0% of the variance" in text
    assert vqvae_verdict({"recon_nmse": 0.3, "psnr_db": 24.0}, True, 0.05)[0] == "passed"  # beats the mean frame
    status, text = vqvae_verdict({"recon_nmse": 1.2, "psnr_db": 9.0}, True, 0.05)
    assert status == "failed" and "no better than the mean frame" in text and "PSNR 9.0 dB" in text
    assert vqvae_verdict({}, False, 0.05)[0] == "failed"
