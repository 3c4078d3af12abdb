"""An evaluation folder written before a plan field existed resumes once the field is added at the value that
reproduces the old behaviour, and is refused (naming the field) when the field is set to anything else; a killed
evaluation resumes from the units it finished."""
import dataclasses
import hashlib
import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from roken.config import load_config
from roken.configtools import LATER_FIELDS, with_later_fields, without_later_fields
from roken.data.store import StoreError
from roken.eval import folder, harness
from roken.plan.rollout import PlanConfig

ROOT = Path(__file__).resolve().parents[1]
# the plan fields of the first evaluation folders (git cda34c2 .. 7cc6f69, 2026-11-23 .. 12-01): a field added
# since is either in configtools.LATER_FIELDS (with its old value) or, where no value gives the old behaviour (the
# guidance fields came with the roken+guided rows), listed here knowingly
BASE_PLAN = {"checkpoint", "which", "replan_every", "cluster_size", "cluster_new", "sensing_range", "accumulate",
             "candidates", "select", "fallback", "sampler", "steps", "device", "dtype", "batch_size", "seed",
             "record_plans", "guide", "guide_scale", "guide_steps", "guide_iters", "guide_final_iters", "guide_lr",
             "guide_margin", "guide_obstacle", "guide_inter", "guide_connect", "guide_goal", "guide_exec_weight"}


def test_every_plan_field_is_base_or_registered():
    later = {k.split(".", 1)[1]: v for k, v in LATER_FIELDS if k.startswith("plan.")}
    fields = {f.name: f.default for f in dataclasses.fields(PlanConfig)}
    assert set(fields) == BASE_PLAN | set(later), "a new plan.* field: append it to configtools.LATER_FIELDS"
    assert not BASE_PLAN & set(later)
    assert all(type(fields[k]) is type(v) for k, v in later.items())  # a value of the field's own type


def test_later_fields_helpers():
    d = {"plan": {"seed": 0, "geo_inflate": 0.0, "geo_inflate_weight": 5.0}, "eval": {"episodes": 3}}
    assert with_later_fields({"plan": {"seed": 0}})["plan"]["geo_inflate"] == 0.0
    assert "plan" not in with_later_fields({"eval": {}})  # a section the config does not hold stays absent
    assert without_later_fields(d)["plan"] == {"seed": 0, "geo_inflate_weight": 5.0}  # not at its old value: kept
    assert without_later_fields(d, len(LATER_FIELDS)) == d and d["plan"]["geo_inflate"] == 0.0  # d untouched


def _cfg(*sets):
    return load_config(None, ["eval.planner=roken", "eval.robots=[2]", "eval.episodes=1", "eval.num_maps=1",
                              f"plan.checkpoint={ROOT / 'models' / 'roken-cpu-four'}", "plan.steps=2",
                              "expert.step_limit_factor=0.2", *sets])


def _as_written_before_geo_inflate(out: Path, cfg, model_id: str) -> None:
    """Rewrite `out` as the code of 2026-12-03 (before plan.geo_inflate) wrote it: its metrics.json config
    without the fields added since, the episode file's fingerprint hashed without them (as that code did)."""
    later = [k for k, _ in LATER_FIELDS]
    since = [k.split(".", 1) for k in later[later.index("plan.geo_inflate"):]]  # geo_inflate and every field after it
    m = json.loads((out / "metrics.json").read_text())
    for section, key in since:
        m["config"].get(section, {}).pop(key, None)
    (out / "metrics.json").write_text(json.dumps(m))
    d = folder._fingerprint_dict(cfg, "roken", model_id)
    for section, key in since:
        d.get(section, {}).pop(key, None)
    old_fp = hashlib.sha256(json.dumps([d, 2], sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = out / "episodes" / "roken-n02.parquet"
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    meta[b"fingerprint"] = json.dumps(old_fp).encode()
    pq.write_table(table.replace_schema_metadata(meta), path)
    assert old_fp not in harness.fingerprints(cfg, 2, "roken", model_id)[-1:]  # not the full hash of today's fields


def test_a_folder_from_before_a_field_resumes_and_another_value_is_refused(tmp_path, capsys):
    out = tmp_path / "ev"
    cfg = _cfg()
    first = harness.evaluate(cfg, out)
    _, model_id = harness.load_model(cfg)
    _as_written_before_geo_inflate(out, cfg, model_id)
    before = (out / "episodes" / "roken-n02.parquet").read_bytes()
    capsys.readouterr()
    again = harness.evaluate(cfg, out)  # the same command after the field was added at its default
    assert "reusing" in capsys.readouterr().err
    assert (out / "episodes" / "roken-n02.parquet").read_bytes() == before  # reused, not re-run
    assert json.dumps(again["planners"]["roken"]) == json.dumps(first["planners"]["roken"])  # NaN length alike
    _as_written_before_geo_inflate(out, cfg, model_id)
    before = (out / "episodes" / "roken-n02.parquet").read_bytes()
    with pytest.raises(StoreError, match=r"plan\.geo_inflate: 0\.0 -> 3\.0"):
        harness.evaluate(_cfg("plan.geo_inflate=3.0"), out)
    assert (out / "episodes" / "roken-n02.parquet").read_bytes() == before  # nothing overwritten
    # a file written with today's full field set (every field hashed) resumes as well
    fps = harness.fingerprints(cfg, 2, "roken", model_id)
    assert fps[0] == harness.fingerprint(cfg, 2, "roken", model_id) and len(fps) > 1
    path = out / "episodes" / "roken-n02.parquet"
    table = pq.read_table(path)
    pq.write_table(table.replace_schema_metadata(dict(table.schema.metadata) | {b"fingerprint": json.dumps(
        fps[-1]).encode()}), path)
    capsys.readouterr()
    harness.evaluate(cfg, out)
    assert "reusing" in capsys.readouterr().err


class _KilledAfterOneUnit(harness.InProcessRunner):
    """In-process runner that dies (as a Ctrl-C or a lost node would) once its first unit has come back."""

    def imap_unordered(self, fn_ref, ctx, units):
        yield next(super().imap_unordered(fn_ref, ctx, units))
        raise KeyboardInterrupt


class _Counting(harness.InProcessRunner):
    def imap_unordered(self, fn_ref, ctx, units):
        units = list(units)
        self.ran = [u.key for u in units]
        yield from super().imap_unordered(fn_ref, ctx, units)


def test_a_killed_evaluation_resumes_from_its_finished_units(tmp_path, capsys):
    cfg = load_config(None, ["eval.robots=[2]", "eval.episodes=4", "eval.num_maps=2", "eval.unit_episodes=2",
                             "expert.step_limit_factor=0.5"])
    whole = harness.evaluate(cfg, tmp_path / "whole")
    with pytest.raises(KeyboardInterrupt):
        harness.evaluate(cfg, tmp_path / "cut", runner=_KilledAfterOneUnit())
    out = tmp_path / "cut"
    assert not (out / "episodes" / "n02.parquet").exists()  # nothing half-written where readers look
    assert len(list((out / "episodes" / "_units").glob("*.parquet"))) == 1
    runner = _Counting()
    again = harness.evaluate(cfg, out, runner=runner)
    assert runner.ran == ["laplacian-n02-u001"]  # only the unit the killed run had not finished
    assert "resuming 2 episodes" in capsys.readouterr().err
    a = pq.read_table(tmp_path / "whole" / "episodes" / "n02.parquet").to_pylist()
    b = pq.read_table(out / "episodes" / "n02.parquet").to_pylist()
    assert a == b and again["full_success"] == whole["full_success"]
    assert not (out / "episodes" / "_units").exists()  # merged into the team size's file, then removed
