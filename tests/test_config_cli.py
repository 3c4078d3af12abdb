import json

import pytest
from conftest import cli

from roken.config import ConfigError, load_config


def test_defaults_are_the_paper_values():
    cfg = load_config()
    assert (cfg.task.comm_radius, cfg.task.d_coll_min, cfg.task.d_obs_min, cfg.task.eps_goal) == (15, 2, 1, 1)
    assert cfg.task.max_step == 0.5 and cfg.map.canvas == 140 and cfg.map.size == 100
    assert (cfg.map.train_maps, cfg.map.eval_maps) == (5000, 1000)


def test_yaml_and_overrides(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("eval:\n  robots: [2, 4]\nexpert:\n  batch_size: 16\n")
    cfg = load_config(f, ["eval.robots=2,4,8", "task.comm_radius=12", "map.families={blocks: 1, maze: 2}"])
    assert cfg.eval.robots == [2, 4, 8] and cfg.expert.batch_size == 16 and cfg.task.comm_radius == 12.0
    assert cfg.map.families == {"blocks": 1.0, "maze": 2.0}


@pytest.mark.parametrize("text,override,needle", [
    ("eval:\n  robtos: [2]\n", [], "eval.robtos"),
    ("", ["expert.nope=1"], "unknown key 'nope'"),
    ("", ["eval.episodes=many"], "eval.episodes"),
    ("- a\n- b\n", [], "mapping"),
])
def test_config_errors_name_the_key(tmp_path, text, override, needle):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        load_config(f, override)


def test_evaluate_command_end_to_end(tmp_path):
    out = tmp_path / "run"
    args = ["--planner", "laplacian", "--robots", "2,3", "--episodes", "3", "--maps", "eval", "--out", str(out),
            "--set", "expert.batch_size=4"]
    r = cli("evaluate.py", *args)
    assert r.returncode == 0, r.stderr
    assert "full succ" in r.stdout and "laplacian" in r.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    for k in ("full_success", "obstacle_collision", "inter_collision", "connectivity", "reach", "length",
              "episodes", "config"):
        assert k in metrics
    assert metrics["episodes"] == 6 and set(metrics["by_team_size"]) == {"2", "3"}
    # recompute the metrics independently from the stored episodes and maps
    from roken.data.store import read_run
    from roken.eval.metrics import episode_metrics, summarize
    from roken.world.tasks import TaskConfig

    maps, eps = read_run(out)
    rows = [episode_metrics(e["positions"], maps[e["map_id"]], e["goal"], e["leader"], TaskConfig()) for e in eps]
    again = summarize(rows)
    for k in ("full_success", "reach", "connectivity"):
        assert again[k] == pytest.approx(metrics[k])
    # resume: the same command reuses the stored episodes
    r2 = cli("evaluate.py", *args)
    assert r2.returncode == 0 and "reusing" in r2.stderr
    png = tmp_path / "ep.png"
    r3 = cli("roken", "plot", str(out), "--index", "1", "--out", str(png))
    assert r3.returncode == 0, r3.stderr
    assert png.stat().st_size > 10_000


def test_evaluate_command_bad_input(tmp_path):
    r = cli("evaluate.py", "--maps", str(tmp_path / "none"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "no map files found" in r.stderr
    r = cli("evaluate.py", "--set", "eval.bogus=1", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "bogus" in r.stderr


def test_external_folder_with_a_corrupt_map(tmp_path):
    import numpy as np

    good = np.zeros((60, 60), np.uint8)
    np.save(tmp_path / "good.npy", good)
    (tmp_path / "broken.map").write_text("type octile\nheight 3\n")
    out = tmp_path / "run"
    r = cli("evaluate.py", "--maps", str(tmp_path), "--robots", "2", "--episodes", "2", "--out", str(out))
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert [b["file"].endswith("broken.map") for b in metrics["bad_maps"]] == [True]
    assert metrics["episodes"] == 2
