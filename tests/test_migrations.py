"""Alembic migrations of the registry: up and down, schema == models, idempotent, safe when several
processes start at once."""
from __future__ import annotations

import fcntl
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Column, Integer, MetaData, inspect

import migrations
from registry import runs
from registry.db import Registry, _alembic_config, current_revision, downgrade, make_engine, migrate
from registry.models import Base
from hope_models.settings import load_settings

REPO = Path(__file__).resolve().parents[1]
TABLES = {"runs", "run_events", "models", "learning_state", "system_samples", "workers"}


def head() -> str:
    return ScriptDirectory(str(Path(migrations.__file__).parent)).get_current_head()


def tables(engine) -> set[str]:
    return set(inspect(engine).get_table_names()) - {"alembic_version"}


def diffs(engine, metadata: MetaData) -> list:
    with engine.connect() as c:
        return compare_metadata(MigrationContext.configure(c, opts={"compare_type": True}), metadata)


@pytest.fixture
def engine(tmp_path):
    eng = make_engine(tmp_path / "hope.db")
    yield eng
    eng.dispose()


def test_single_linear_history():
    script = ScriptDirectory(str(Path(migrations.__file__).parent))
    assert len(script.get_heads()) == 1
    assert [r.revision for r in script.walk_revisions()][-1] == "0001"


def test_empty_to_head_to_base_to_head(engine):
    assert tables(engine) == set() and current_revision(engine) is None
    migrate(engine)
    assert tables(engine) == TABLES and current_revision(engine) == head()
    downgrade(engine)
    assert tables(engine) == set() and current_revision(engine) is None
    migrate(engine, "head")
    assert tables(engine) == TABLES and current_revision(engine) == head()


def test_head_schema_matches_models(engine):
    migrate(engine)
    assert diffs(engine, Base.metadata) == []
    # the comparison is able to see a difference (so the empty list above means something)
    changed = MetaData(naming_convention=Base.metadata.naming_convention)
    for table in Base.metadata.sorted_tables:
        table.to_metadata(changed)
    changed.tables["runs"].append_column(Column("extra", Integer))
    assert [d[0] for d in diffs(engine, changed)] == ["add_column"]


def test_head_schema_details(engine):
    migrate(engine)
    with engine.connect() as c:
        sql = dict(c.exec_driver_sql("SELECT name, sql FROM sqlite_master WHERE type='index' AND sql IS NOT NULL").all())
    # the partial unique index (one promoted model per component); autogenerate does not compare WHERE
    assert "WHERE promoted_at IS NOT NULL" in sql["uq_models_promoted_component"]
    assert "UNIQUE" in sql["uq_models_promoted_component"]
    assert sql["ix_runs_dispatch"].endswith("(state, queue, priority, created_at)")
    names = {fk["name"] for fk in inspect(engine).get_foreign_keys("run_events")}
    assert names == {"fk_run_events_run_id_runs"}  # the naming convention is applied


def test_migrate_is_idempotent_and_keeps_data(tmp_path):
    settings = load_settings(tmp_path / "home", env={})
    with Registry.open(settings) as reg:
        with reg.session() as s:
            rid = runs.create_run(s, component="vqvae", config={}, total_steps=5, run_dir="/r").id
    for _ in range(2):
        migrate(tmp_path / "home" / "hope.db")  # a path works as well as an engine
        with Registry.open(settings) as reg:
            assert current_revision(reg.engine) == head()
            with reg.session(readonly=True) as s:
                assert runs.get_run(s, rid).total_steps == 5
            with reg.engine.connect() as c:
                assert c.exec_driver_sql("SELECT count(*) FROM alembic_version").scalar() == 1


def test_migration_failure_rolls_back(engine, tmp_path):
    """One transaction per migrate(): a failing step leaves the database as it was."""
    migrate(engine)
    with engine.begin() as c:
        c.exec_driver_sql("CREATE TABLE blocker (x INTEGER)")
    downgrade(engine)
    with engine.begin() as c:  # make the upgrade fail half-way: models' index name is taken
        c.exec_driver_sql("CREATE INDEX ix_run_events_run_id ON blocker (x)")
    with pytest.raises(Exception, match="ix_run_events_run_id"):
        migrate(engine)
    assert tables(engine) == {"blocker"} and current_revision(engine) is None


MIGRATOR = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from registry.db import migrate
    db, go = Path(sys.argv[1]), Path(sys.argv[2])
    while not go.exists():
        time.sleep(0.002)
    migrate(db)
    print("torch" in sys.modules)
    """
)


def _spawn(db: Path, go: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", MIGRATOR, str(db), str(go)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_processes_migrating_at_once(tmp_path):
    db, go = tmp_path / "hope.db", tmp_path / "go"
    procs = [_spawn(db, go) for _ in range(3)]
    time.sleep(0.3)  # let them import and wait at the start line
    go.touch()
    for p in procs:
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, f"a concurrent migrate failed:\n{err}"
        assert out.strip() == "False", "migrating must not import torch"
    eng = make_engine(db)
    try:
        assert tables(eng) == TABLES and current_revision(eng) == head()
        assert diffs(eng, Base.metadata) == []
    finally:
        eng.dispose()


def test_migrate_waits_for_the_lock(tmp_path):
    db, go = tmp_path / "hope.db", tmp_path / "go"
    go.touch()
    with open(tmp_path / "hope.db.migrate.lock", "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)  # another process is migrating
        proc = _spawn(db, go)
        time.sleep(1.0)
        assert proc.poll() is None, "migrate did not wait for the migrate lock"
        assert not db.exists() or current_revision_of(db) is None
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert current_revision_of(db) == head()


def current_revision_of(db: Path) -> str | None:
    eng = make_engine(db)
    try:
        return current_revision(eng)
    finally:
        eng.dispose()


def test_alembic_config_points_at_the_package(engine):
    with engine.connect() as c:
        cfg = _alembic_config(c)
    assert Path(cfg.get_main_option("script_location")) == Path(migrations.__file__).resolve().parent


def _columns(engine, table: str) -> set[str]:
    return {c["name"] for c in inspect(engine).get_columns(table)}


def test_0002_promotion_columns_up_and_down_keep_the_data(engine):
    """0002 adds the promotion history and loop-closure columns; up and down keep every row (the
    downgrade must not copy `runs`: with foreign keys on that would cascade-delete run_events)."""
    import sqlalchemy as sa

    migrate(engine, "0001")
    with engine.begin() as c:
        c.exec_driver_sql("INSERT INTO runs (id, component, config, state, total_steps, run_dir, created_at, updated_at) "
                          "VALUES ('r1', 'fast_loop', '{}', 'completed', 5, '/r', '2026-01-01', '2026-01-01')")
        c.exec_driver_sql("INSERT INTO run_events (run_id, time, kind, payload) VALUES ('r1', '2026-01-01', 'log', '{}')")
        c.exec_driver_sql("INSERT INTO models (component, checkpoint_path, run_id, promoted_at, created_at) "
                          "VALUES ('fast_loop', '/c', 'r1', '2026-01-01', '2026-01-01')")
    migrate(engine, "0002")
    assert {"version", "demoted_at", "previous_model_id"} <= _columns(engine, "models")
    assert {"first_inference_at", "loop_closure_s"} <= _columns(engine, "runs")
    fks = {fk["name"]: fk for fk in inspect(engine).get_foreign_keys("models")}
    assert fks["fk_models_previous_model_id_models"]["referred_table"] == "models"
    with engine.begin() as c:
        assert c.exec_driver_sql("SELECT run_id, promoted_at IS NOT NULL, version FROM models").all() == [("r1", 1, None)]
        assert c.exec_driver_sql("SELECT count(*) FROM run_events").scalar() == 1
        sql = c.exec_driver_sql("SELECT sql FROM sqlite_master WHERE name='uq_models_promoted_component'").scalar()
        assert "WHERE promoted_at IS NOT NULL" in sql  # survived the table copy
        c.exec_driver_sql("INSERT INTO models (component, checkpoint_path, created_at, previous_model_id) "
                          "VALUES ('fast_loop', '/d', '2026-01-02', 1)")
    with pytest.raises(sa.exc.IntegrityError), engine.begin() as c:  # still one promoted model per component
        c.exec_driver_sql("UPDATE models SET promoted_at = '2026-01-02' WHERE id = 2")
    downgrade(engine, "0001")
    assert "version" not in _columns(engine, "models") and "loop_closure_s" not in _columns(engine, "runs")
    with engine.begin() as c:
        assert c.exec_driver_sql("SELECT count(*) FROM run_events").scalar() == 1
        assert c.exec_driver_sql("SELECT run_id FROM models ORDER BY id").all() == [("r1",), (None,)]
        sql = c.exec_driver_sql("SELECT sql FROM sqlite_master WHERE name='uq_models_promoted_component'").scalar()
        assert "WHERE promoted_at IS NOT NULL" in sql
    migrate(engine)
    assert current_revision(engine) == head()
    assert diffs(engine, Base.metadata) == []


def test_0003_unclaimed_running_runs_become_starting_and_back(engine):
    """0003 adds runs.dispatched_at and the `starting` state: a run that 0002's rules left running
    with no worker pid (sent, never claimed) is starting after the upgrade, so claim(), cancel and
    the re-send treat it by the new rules; a claimed one stays running. Down reverses it, keeping
    every row and event."""
    migrate(engine, "0002")
    with engine.begin() as c:
        for rid, pid in (("sent", None), ("claimed", 4242)):
            c.exec_driver_sql("INSERT INTO runs (id, component, config, state, total_steps, run_dir, worker_pid, "
                              "celery_task_id, heartbeat_at, created_at, updated_at) VALUES (?, 'fast_loop', '{}', "
                              "'running', 5, '/r', ?, 't-1', '2026-01-01 10:00:00.000000', '2026-01-01', "
                              "'2026-01-01')", (rid, pid))
        c.exec_driver_sql("INSERT INTO run_events (run_id, time, kind, payload) VALUES ('sent', '2026-01-01', 'log', '{}')")
    migrate(engine, "0003")
    with engine.begin() as c:
        rows = c.exec_driver_sql("SELECT id, state, dispatched_at FROM runs ORDER BY id").all()
    assert rows == [("claimed", "running", None), ("sent", "starting", "2026-01-01 10:00:00.000000")]
    downgrade(engine, "0002")
    assert "dispatched_at" not in _columns(engine, "runs")
    with engine.begin() as c:
        assert c.exec_driver_sql("SELECT id, state FROM runs ORDER BY id").all() == [("claimed", "running"),
                                                                                      ("sent", "running")]
        assert c.exec_driver_sql("SELECT count(*) FROM run_events").scalar() == 1
    migrate(engine)
    assert diffs(engine, Base.metadata) == []


def test_an_upgrade_backs_the_registry_up_first(tmp_path):
    """Before an existing registry is migrated, a copy of it as it was is kept beside it; a new
    registry, or one already at head, gets none."""
    import sqlite3

    db = tmp_path / "hope.db"
    eng = make_engine(db)
    try:
        migrate(eng)
        assert sorted(p.name for p in tmp_path.glob("hope.db.before-*")) == []  # new: nothing to keep
        script = ScriptDirectory(str(Path(migrations.__file__).parent))
        older = script.get_revision(head()).down_revision
        downgrade(eng, older)
        with eng.begin() as c:
            c.exec_driver_sql("INSERT INTO runs (id, component, state, queue, priority, total_steps, step, attempt, "
                              "max_attempts, run_dir, config, created_at, updated_at) VALUES ('r-old', 'vqvae', "
                              "'queued', 'pi', 0, 5, 0, 0, 3, '/r', '{}', '2026-01-01', '2026-01-01')")
        migrate(eng)
        backups = sorted(tmp_path.glob("hope.db.before-*"))
        assert [p.name for p in backups] == [f"hope.db.before-{head()}-from-{older}"]
        kept = sqlite3.connect(backups[0])
        try:  # the copy is the registry as it was: the old revision, with its rows
            assert kept.execute("SELECT version_num FROM alembic_version").fetchone()[0] == older
            assert kept.execute("SELECT id FROM runs").fetchall() == [("r-old",)]
        finally:
            kept.close()
        migrate(eng)  # at head: no second copy
        assert len(list(tmp_path.glob("hope.db.before-*"))) == 1
    finally:
        eng.dispose()


def test_0004_learning_state_up_and_down(engine):
    """0004 adds the continuous-learning row (pause, phase, watermark), which must survive a restart:
    what one process writes another reads, and a downgrade drops only that table."""
    from registry import learning
    from sqlalchemy.orm import Session

    migrate(engine, "0003")
    with engine.begin() as c:
        c.exec_driver_sql("INSERT INTO runs (id, component, config, state, total_steps, run_dir, created_at, updated_at) "
                          "VALUES ('r1', 'fast_loop', '{}', 'queued', 5, '/r', '2026-01-01', '2026-01-01')")
    assert "learning_state" not in tables(engine)
    migrate(engine, "0004")
    assert "learning_state" in tables(engine)
    migrate(engine)  # the ORM's models are head's (0006 added reset_at): read and write the row through them
    with Session(engine) as s, s.begin():
        learning.pause(s)
        learning.record_auto_run(s, "s-1", "auto-train: because", {"fast_loop": ["ep-a", "ep-b"]})
    with Session(engine) as s:  # another session (process) reads what the first wrote
        assert learning.is_paused(s) and learning.watermark(s) == {"fast_loop": {"ep-a", "ep-b"}}
        assert learning.read(s).last_auto_reason == "auto-train: because"
    downgrade(engine, "0003")
    assert "learning_state" not in tables(engine)
    with engine.begin() as c:
        assert c.exec_driver_sql("SELECT id, state FROM runs").all() == [("r1", "queued")]
    migrate(engine)
    assert diffs(engine, Base.metadata) == []


def test_0006_reset_at_keeps_the_learning_row(engine):
    """0006 adds learning_state.reset_at (the app's reset, registry/learning.reset): a row written
    before reads as never reset, and a downgrade drops only the column, keeping the row."""
    from registry import learning
    from sqlalchemy.orm import Session

    migrate(engine, "0005")
    with engine.begin() as c:
        c.exec_driver_sql("INSERT INTO learning_state (id, paused, phase, watermark, last_auto_sequence_id, updated_at) "
                          "VALUES (1, 1, 'idle', '{\"fast_loop\": [\"ep-a\"]}', 's-1', '2026-01-01')")
    migrate(engine, "0006")
    with Session(engine) as s, s.begin():
        assert learning.reset_at(s) is None and learning.watermark(s) == {"fast_loop": {"ep-a"}}
        out = learning.reset(s)
        assert out["forgot_watermark"] == {"fast_loop": 1} and out["forgot_last_auto_run"] == "s-1"
    with Session(engine) as s:
        assert learning.reset_at(s) is not None and learning.watermark(s) == {} and learning.is_paused(s)
    downgrade(engine, "0005")
    with engine.begin() as c:
        assert c.exec_driver_sql("SELECT id, paused FROM learning_state").all() == [(1, 1)]
        assert "reset_at" not in [r[1] for r in c.exec_driver_sql("PRAGMA table_info(learning_state)").all()]
    migrate(engine)
    assert diffs(engine, Base.metadata) == []
