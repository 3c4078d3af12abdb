"""cluster/ checked offline: the launcher YAML against the schema shipped in the Ray wheel, the KubeRay
RayJobs' structure, token auth and entrypoints (parsed by the pipelines' own argument parsers)."""
import re
import shlex
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import load_pipeline

from roken.config import load_config

ROOT = Path(__file__).resolve().parents[1]
CLUSTER = ROOT / "cluster"


def test_launcher_yaml_passes_rays_own_validation():
    from ray.autoscaler._private.util import prepare_config, validate_config

    cfg = yaml.safe_load((CLUSTER / "launcher.yaml").read_text())
    validate_config(prepare_config(cfg))  # jsonschema: ray/autoscaler/ray-schema.json, plus Ray's checks
    assert cfg["head_node_type"] in cfg["available_node_types"]
    for cmds in (cfg["head_start_ray_commands"], cfg["worker_start_ray_commands"]):
        start = [c for c in cmds if "ray start" in c]
        assert start and all("RAY_AUTH_MODE=token" in c for c in start)
    assert any("--dashboard-host=127.0.0.1" in c for c in cfg["head_start_ray_commands"])
    assert "~/.ray/auth_token" in cfg["file_mounts"].values()
    bad = dict(cfg, max_wokers=3)  # a typo must not pass
    with pytest.raises(Exception, match="max_wokers"):
        validate_config(prepare_config(bad))


@pytest.mark.parametrize("name,pipeline", [("rayjob-generate.yaml", "generate"),
                                           ("rayjob-evaluate.yaml", "evaluate")])
def test_kuberay_rayjob(name, pipeline):
    doc = yaml.safe_load((CLUSTER / "kuberay" / name).read_text())
    assert doc["apiVersion"] == "ray.io/v1" and doc["kind"] == "RayJob"
    spec = doc["spec"]
    assert spec["shutdownAfterJobFinishes"] is True
    yaml.safe_load(spec["runtimeEnvYAML"])
    rc = spec["rayClusterSpec"]
    pods = [rc["headGroupSpec"]["template"]] + [g["template"] for g in rc["workerGroupSpecs"]]
    for pod in pods:
        for c in pod["spec"]["containers"]:
            env = {e["name"]: e for e in c["env"]}
            assert env["RAY_AUTH_MODE"]["value"] == "token"
            assert "secretKeyRef" in env["RAY_AUTH_TOKEN"]["valueFrom"]  # the token is never inline
            assert c["image"] and c["resources"]["limits"]["cpu"]
    for g in rc["workerGroupSpecs"]:
        assert g["minReplicas"] <= g["replicas"] <= g["maxReplicas"]
    tokens = shlex.split(spec["entrypoint"])
    assert tokens[:2] == ["python", f"pipelines/{pipeline}.py"]
    mod = load_pipeline(pipeline)
    args = mod.parser().parse_args(tokens[2:])  # the real flags: a renamed flag breaks this test
    load_config(args.config, mod.overrides(args))  # and the values fit the config schema
    assert args.out.startswith("s3://")


def test_one_ray_version_everywhere():
    versions = set(re.findall(r"rayproject/ray:(\d+\.\d+\.\d+)", (CLUSTER / "launcher.yaml").read_text()
                              + (CLUSTER / "Dockerfile").read_text()))
    for f in (CLUSTER / "kuberay").glob("*.yaml"):
        versions.add(yaml.safe_load(f.read_text())["spec"]["rayClusterSpec"]["rayVersion"])
    assert len(versions) == 1, versions
    (v,) = versions
    major, minor = map(int, v.split(".")[:2])
    assert (2, 55) <= (major, minor) < (3, 0)  # inside pyproject's ray range


def test_runtime_env_keeps_data_and_history_out_of_job_uploads():
    env = yaml.safe_load((CLUSTER / "runtime_env.yaml").read_text())
    assert set(env) <= {"excludes", "env_vars", "pip", "working_dir"}
    from ray._private.runtime_env.packaging import _get_excludes

    ignored = _get_excludes(ROOT, env["excludes"])  # Ray's own matcher for the upload
    for path in (".git/HEAD", "data/x.parquet", "checkpoints/model.pt", ".venv/bin/python", "runs/a/m.json"):
        assert ignored(ROOT / path), path
    tracked = subprocess.run(["git", "-C", str(ROOT), "ls-files"], capture_output=True, text=True).stdout.split()
    code = [p for p in tracked if p.endswith((".py", ".yaml", ".sh"))] or \
        [str(p.relative_to(ROOT)) for p in ROOT.glob("roken/**/*.py")]
    assert any(p.startswith("roken/data/") for p in code)
    dropped = [p for p in code if ignored(ROOT / p)]
    assert not dropped, f"the job upload would leave out {dropped[:5]}"
