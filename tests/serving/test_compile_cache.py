"""Warm starts (issue 77): torch's compile caches in a folder of the server's, used only by a start of the same
settings and versions. A real compile in fresh processes (each start is one: nothing in memory carries over), and
the service's record of what its graphs depend on."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hf_specvla.serving import PolicyService, ServeConfig
from hf_specvla.serving.compile_cache import RECORD_FILE, CompileCache

POLICY = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla3"

#: one start: a function compiled inside the cache of ``record``, then what torch's caches did
START = textwrap.dedent("""
    import json, logging, sys
    import torch
    from torch._dynamo.utils import counters
    from hf_specvla.serving.compile_cache import CompileCache

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    root, settings = sys.argv[1], sys.argv[2]
    with CompileCache(root, {"torch": torch.__version__, "settings": settings}).compiling() as warm:
        compiled = torch.compile(lambda x: (x.sin() * 2 + x.cos()).sum(-1))
        result = compiled(torch.arange(12.0).reshape(3, 4))
    eager = (torch.arange(12.0).reshape(3, 4).sin() * 2 + torch.arange(12.0).reshape(3, 4).cos()).sum(-1)
    print(json.dumps({"warm": warm, "hits": counters["inductor"]["fxgraph_cache_hit"],
                      "misses": counters["inductor"]["fxgraph_cache_miss"], "equal": bool(torch.equal(result, eager))}))
""")


def _start(root: Path, settings: str, default_cache: Path) -> tuple[dict, str]:
    """A fresh process's start (its own default Inductor folder: only the compile cache can carry a compile over)."""
    env = {"TORCHINDUCTOR_CACHE_DIR": str(default_cache), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    result = subprocess.run([sys.executable, "-c", START, str(root), settings], capture_output=True, text=True,
                            timeout=300, env=env)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1]), result.stderr


@pytest.mark.commands  # ~35 s: three fresh processes, each compiling
def test_a_second_start_of_the_same_settings_reuses_the_compile_and_another_settings_never_does(tmp_path):
    root = tmp_path / "cache"
    first, first_log = _start(root, "buckets 1 2 4", tmp_path / "default1")
    second, second_log = _start(root, "buckets 1 2 4", tmp_path / "default2")
    other, other_log = _start(root, "buckets 1 2", tmp_path / "default3")
    assert (first["warm"], first["hits"], first["misses"]) == (False, 0, 1)
    assert (second["warm"], second["hits"], second["misses"]) == (True, 1, 0)  # Inductor's graph from the folder
    assert (other["warm"], other["hits"], other["misses"]) == (False, 0, 1)  # never another settings' graph
    assert first["equal"] and second["equal"] and other["equal"]
    assert "cold, compiling into" in first_log and "warm" in second_log
    assert "other settings' caches, not used" in other_log and "settings 'buckets 1 2 4' there, 'buckets 1 2' here" in (
        other_log
    )
    assert len(list(root.glob(f"*/{RECORD_FILE}"))) == 2  # one folder per settings: neither replaced


def test_a_warm_up_that_fails_records_nothing(tmp_path):
    cache = CompileCache(tmp_path, {"settings": 1})
    with pytest.raises(RuntimeError, match="interrupted"), cache.compiling():
        raise RuntimeError("interrupted")
    assert not cache.warm and not (cache.folder / RECORD_FILE).exists()


def test_the_services_record_names_what_its_graphs_depend_on(tmp_path):
    from hf_specvla.policies import VLAPolicy

    policy = VLAPolicy.from_pretrained(POLICY)
    settings = dict(method="exact", buckets=(1, 2, 4), calibration_calls=0, compile_cache=str(tmp_path))
    cache = PolicyService(policy, ServeConfig(**settings)).compile_cache()
    record = cache.record
    assert record["policy"] == policy.weights_fingerprint() and record["draft_head"] is None
    assert record["methods"] == ["greedy:compile", "prior+jacobi:compile"] and record["buckets"] == [1, 2, 4]
    assert {"torch", "transformers", "python", "hf_specvla", "device", "prompt_tiers"} <= set(record)
    other = PolicyService(policy, ServeConfig(**{**settings, "buckets": (1, 2)})).compile_cache()
    assert other.key != cache.key and other.folder.parent == cache.folder.parent == tmp_path


def test_an_eager_method_compiles_nothing_and_says_the_cache_is_not_used(tmp_path, caplog):
    from hf_specvla.policies import VLAPolicy

    policy = VLAPolicy.from_pretrained(POLICY)
    service = PolicyService(policy, ServeConfig(method="prior+jacobi", buckets=(1,), calibration_calls=0,
                                                compile_cache=str(tmp_path)))  # fmt: skip
    assert service.compile_cache() is None
    with caplog.at_level(logging.INFO, logger="hf_specvla"):
        service.warm_up()
    service.close()
    assert f"compile cache {tmp_path} not used: prior+jacobi compiles nothing" in caplog.text
    assert service.info()["startup"]["compile_cache"] is None and service.info()["startup"]["compile_s"] >= 0
    assert not list(tmp_path.iterdir())
