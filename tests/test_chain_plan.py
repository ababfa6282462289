"""plan_chain: the one decision of where each member of a chain gets its VQ-VAE, which both runners
(`train --sequential`'s children, create_sequence's queued runs) execute."""
from __future__ import annotations

import argparse

import pytest

from hope_models.components import COMPONENTS, NEEDS_VQVAE, TOKENIZER
from hope_models.components.chain import (VQVAE_GIVEN, VQVAE_MEMBER, VQVAE_NONE, ChainStep, parse_sequence,
                                          plan_chain, tokenizer_missing)

FULL = list(COMPONENTS)  # the table's order: the tokenizer before its readers
READERS = [n for n in FULL if COMPONENTS[n].reads_vqvae != "never"]
NEEDS = next(n for n in FULL if n in NEEDS_VQVAE)
OPTIONAL = [n for n in FULL if COMPONENTS[n].reads_vqvae == "optional"]


def test_full_chain_readers_get_the_tokenizer_member():
    plan = plan_chain(parse_sequence(",".join(FULL)), given=False)
    tok = FULL.index(TOKENIZER)
    assert [s.name for s in plan] == FULL
    for step in plan:
        if step.name in READERS:
            assert step == ChainStep(step.name, VQVAE_MEMBER, member=tok, reads_vqvae=True)
        else:
            assert step == ChainStep(step.name, VQVAE_NONE)
    # a given one does not replace the chain's own tokenizer, unless it comes first (--vqvae DIR)
    assert plan_chain(FULL, given=True) == plan
    assert all(s.vqvae == VQVAE_GIVEN for s in plan_chain(FULL, given=True, given_first=True) if s.name in READERS)


def test_chain_without_the_tokenizer_but_a_given_vqvae():
    plan = plan_chain(READERS, given=True)
    assert plan == [ChainStep(n, VQVAE_GIVEN, reads_vqvae=True) for n in READERS]
    assert tokenizer_missing(READERS, True) is None


def test_reader_of_codes_without_any_is_missing():
    plan = plan_chain([*OPTIONAL, NEEDS], given=False)
    assert plan[-1] == ChainStep(NEEDS, VQVAE_NONE, reads_vqvae=True, missing=True)
    assert all(s == ChainStep(s.name, VQVAE_NONE, reads_vqvae=True) for s in plan[:-1])  # they train without
    assert tokenizer_missing([*OPTIONAL, NEEDS], False) == NEEDS


def test_reader_without_any_is_refused_by_both_runners_with_their_messages(tmp_path, capsys):
    from hope_models.settings import load_settings
    from hope_models.train.sequential import run_sequential
    from registry import runs
    from registry.db import Registry
    from registry.sequences import create_sequence

    with Registry.open(load_settings(tmp_path / "home")) as registry, registry.session() as s:
        with pytest.raises(runs.RunError, match=f"components: {NEEDS} needs a trained VQ-VAE: put {TOKENIZER} before "
                                                "it in the chain, or give vqvae_dir / vqvae_run"):
            create_sequence(s, NEEDS, {"data": "ds"}, total_steps=10, runs_dir=tmp_path / "runs")
    (tmp_path / "ds").mkdir()
    args = argparse.Namespace(sequential=NEEDS, data=str(tmp_path / "ds"), run_dir=str(tmp_path / "r"), vqvae=None,
                              json=False)
    assert run_sequential(args) == 2
    assert (f"{NEEDS} needs a trained VQ-VAE: put {TOKENIZER} earlier in --sequential, or pass --vqvae DIR "
            f"(no complete checkpoint under {tmp_path / 'r' / TOKENIZER})") in capsys.readouterr().err


def test_the_tokenizer_alone():
    assert plan_chain([TOKENIZER], given=False) == [ChainStep(TOKENIZER, VQVAE_NONE)]
    assert plan_chain([TOKENIZER], given=True, given_first=True) == [ChainStep(TOKENIZER, VQVAE_NONE)]


def test_create_sequence_executes_the_plan(tmp_path):
    from hope_models.settings import load_settings
    from registry.db import Registry
    from registry.sequences import create_sequence

    with Registry.open(load_settings(tmp_path / "home")) as registry, registry.session() as s:
        created = create_sequence(s, FULL, {"data": "ds", "vqvae_dir": "/given"}, total_steps=10,
                                  runs_dir=tmp_path / "runs")
        plan = plan_chain(FULL, given=True)
        for run, step in zip(created, plan, strict=True):
            assert run.component == step.name
            if step.vqvae == VQVAE_MEMBER:
                assert run.config["vqvae_run"] == created[step.member].id and "vqvae_dir" not in run.config
            else:
                assert "vqvae_run" not in run.config and "vqvae_dir" not in run.config
        readers = create_sequence(s, READERS, {"data": "ds", "vqvae_dir": "/given"}, total_steps=10,
                                  runs_dir=tmp_path / "runs")
        assert all(r.config["vqvae_dir"] == "/given" and "vqvae_run" not in r.config for r in readers)
