"""Warm starts (issue 77): torch's compile caches in a folder of the server's, used only by a start of the same
settings and versions. A real compile in fresh processes (each start is one: nothing in memory carries over), and
the service's record of what its graphs depend on."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import hf_specvla
from hf_specvla.serving import PolicyService, ServeConfig
from hf_specvla.serving.compile_cache import DAMAGED, FILES_FILE, RECORD_FILE, CompileCache

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


def _start(root: Path, settings: str, default_cache: Path, fails: bool = False) -> tuple[dict, str]:
    """A fresh process's start (its own default Inductor folder: only the compile cache can carry a compile over);
    with ``fails``, one that must fail (then only its log)."""
    env = {"TORCHINDUCTOR_CACHE_DIR": str(default_cache), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin",
           "PYTHONPATH": str(Path(hf_specvla.__file__).parents[1])}  # the hf_specvla under test  # fmt: skip
    result = subprocess.run([sys.executable, "-c", START, str(root), settings], capture_output=True, text=True,
                            timeout=300, env=env)  # fmt: skip
    if fails:
        assert result.returncode != 0, result.stdout[-3000:]
        return {}, result.stderr
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
    assert record["methods"] == ["none:compile", "prior+jacobi:compile"] and record["buckets"] == [1, 2, 4]
    assert {"torch", "transformers", "python", "hf_specvla", "device", "prompt_tiers"} <= set(record)
    other = PolicyService(policy, ServeConfig(**{**settings, "buckets": (1, 2)})).compile_cache()
    assert other.key != cache.key and other.folder.parent == cache.folder.parent == tmp_path


def test_a_compiled_services_graph_files_live_in_its_compile_cache(tmp_path, monkeypatch):
    """The warm-up of a service given ``compile_cache=DIR`` keeps the engine's graph files in ``DIR/graphs`` (the one
    folder a warm start needs, Inductor's caches beside them), whatever ``HF_SPECVLA_GRAPH_CACHE`` names; after it the
    folder is the variable's again."""
    from hf_specvla.policies import VLAPolicy
    from hf_specvla.serving.compile_cache import GRAPHS_FOLDER
    from hf_specvla.speculative import graph_files

    monkeypatch.setenv(graph_files.FOLDER_ENV, str(tmp_path / "elsewhere"))
    policy = VLAPolicy.from_pretrained(POLICY)
    service = PolicyService(policy, ServeConfig(method="exact", buckets=(1,), calibration_calls=0,
                                                compile_cache=str(tmp_path / "cache")))  # fmt: skip
    seen = []

    def warm_up(calibrate, seed):  # where the warm-up's graphs would go, without compiling them (fast)
        seen.append(graph_files.graph_folder(policy.model.device.type))
        service.startup.update(compile_s=0.0, calibrate_s=0.0)
        return []

    monkeypatch.setattr(service, "_warm_up", warm_up)
    try:
        service.warm_up()
    finally:
        service.close()
    assert seen == [tmp_path / "cache" / GRAPHS_FOLDER]
    assert graph_files.graph_folder("cpu") == tmp_path / "elsewhere"


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


# ------------------------------------------------------------------------------------- a damaged folder (reliability-6)
#: the "compiled" files of a warm-up without torch's compile (fast): path in Inductor's folder -> bytes
COMPILED = {"fxgraph/f3/f3abc/entry": bytes(range(256)) * 4, "bf/cbf.py": b"def call(args):\n    return args\n" * 20,
            "bf/cbf.so": b"\x7fELF" + bytes(500)}  # fmt: skip


def _compile(cache: CompileCache) -> bool:
    """A start of ``cache`` whose warm-up writes ``COMPILED`` (and a lock file, as torch does) when it is cold;
    returns whether it was warm."""
    with cache.compiling() as warm:
        inductor = cache.folder / "inductor"
        if not warm:
            for name, data in COMPILED.items():
                (inductor / name).parent.mkdir(parents=True, exist_ok=True)
                (inductor / name).write_bytes(data)
            (inductor / "locks").mkdir(exist_ok=True)
            (inductor / "locks" / "cbf.lock").touch()
    return warm


def _contents(folder: Path) -> dict[str, bytes]:
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in folder.rglob("*") if path.is_file()}


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _flip_a_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


#: damage -> (what it does to a warm folder, the file the warning names)
DAMAGES = {
    "an emptied compiled file": (lambda folder: (folder / "inductor/bf/cbf.py").write_bytes(b""), "inductor/bf/cbf.py"),
    "a truncated compiled file": (lambda folder: _truncate(folder / "inductor/fxgraph/f3/f3abc/entry"),
                                  "inductor/fxgraph/f3/f3abc/entry"),
    "a compiled file changed, same size": (lambda folder: _flip_a_byte(folder / "inductor/bf/cbf.so"),
                                           "inductor/bf/cbf.so"),
    "a compiled file missing": (lambda folder: (folder / "inductor/bf/cbf.py").unlink(), "inductor/bf/cbf.py"),
    "a corrupted record": (lambda folder: (folder / RECORD_FILE).write_text('{"settings": '), RECORD_FILE),
    "an emptied record": (lambda folder: (folder / RECORD_FILE).write_bytes(b""), RECORD_FILE),
    "a truncated list of files": (lambda folder: _truncate(folder / FILES_FILE), FILES_FILE),
    "no list of files (an older cache's)": (lambda folder: (folder / FILES_FILE).unlink(), FILES_FILE),
}  # fmt: skip


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_folder_is_set_aside_with_a_warning_and_the_start_compiles_cold_then_warms_again(
    tmp_path, caplog, damage
):
    cache = CompileCache(tmp_path, {"settings": 1})
    assert _compile(cache) is False and cache.warm and cache.damage() is None
    damage_folder, named = DAMAGES[damage]
    damage_folder(cache.folder)
    damaged = _contents(cache.folder)
    assert not cache.warm and named in cache.damage()
    with caplog.at_level(logging.WARNING, logger="hf_specvla"):
        assert _compile(cache) is False  # cold: compiled again into a fresh folder
    aside = cache.set_aside
    assert aside is not None and aside.parent == tmp_path and aside.name.startswith(f"{cache.key}{DAMAGED}")
    assert _contents(aside) == damaged  # set aside as it was: nothing a user saved is lost
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and str(cache.folder) in warnings[0] and named in warnings[0]
    assert f"set aside as {aside}; this start compiles cold" in warnings[0]
    assert cache.warm and _contents(cache.folder / "inductor") == {**COMPILED, "locks/cbf.lock": b""}
    assert cache.others() == []  # a damaged folder is no other settings' cache
    assert _compile(cache) is True and cache.set_aside is None  # the start after: warm, nothing set aside
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([cache.key, aside.name])


def test_files_torch_adds_after_the_record_are_not_damage_and_a_warm_start_lists_them(tmp_path, caplog):
    cache = CompileCache(tmp_path, {"settings": 1})
    _compile(cache)
    inductor = cache.folder / "inductor"
    (inductor / "q6").mkdir()
    (inductor / "q6" / "cq6.cpp").write_text("// a later compile's kernel")  # after the warm-up: not listed
    (inductor / "locks" / "cbf.lock").write_text("held")  # lock files and half-written temporaries come and go
    (inductor / "q6" / ".123.456.tmp").write_text("half")
    (inductor / "locks" / "cq6.lock").touch()
    caplog.clear()  # (an earlier test may have set hf_specvla's loggers to INFO: the first compile's lines)
    with caplog.at_level(logging.WARNING, logger="hf_specvla"):
        assert _compile(cache) is True
    warnings = [record for record in caplog.records if record.levelno >= logging.WARNING]
    assert cache.set_aside is None and not warnings and [p.name for p in tmp_path.iterdir()] == [cache.key]
    listed = json.loads((cache.folder / FILES_FILE).read_text())["files"]
    assert sorted(listed) == sorted(f"inductor/{name}" for name in [*COMPILED, "q6/cq6.cpp"])  # no lock, no tmp
    (inductor / "q6" / "cq6.cpp").write_text("")  # listed by the warm start: its damage is seen now
    assert cache.damage() == "inductor/q6/cq6.cpp has 0 bytes, 27 when recorded"


def test_a_warm_start_that_fails_sets_the_folder_aside_and_says_the_next_start_compiles_cold(tmp_path, caplog):
    cache = CompileCache(tmp_path, {"settings": 1})
    _compile(cache)
    before = _contents(cache.folder)
    with caplog.at_level(logging.WARNING, logger="hf_specvla"), pytest.raises(RuntimeError) as raised:
        with cache.compiling() as warm:
            assert warm
            raise AttributeError("module 'cbf' has no attribute 'call'")  # as Inductor's, from a damaged graph
    aside = cache.set_aside
    assert aside is not None and _contents(aside) == before and not cache.folder.exists()
    message = str(raised.value)
    assert str(cache.folder) in message and f"set aside as {aside}: the next start compiles cold" in message
    assert isinstance(raised.value.__cause__, AttributeError)  # the error itself, chained
    assert str(cache.folder) in caplog.text and str(aside) in caplog.text
    assert _compile(cache) is False and _compile(cache) is True  # cold once, then warm again


def test_a_start_into_an_unfinished_warm_ups_files_that_fails_sets_them_aside_a_fresh_one_keeps_its_error(tmp_path):
    cache = CompileCache(tmp_path, {"settings": 1})
    with pytest.raises(KeyError), cache.compiling():  # a fresh folder: the error is the warm-up's own
        raise KeyError("interrupted")
    assert cache.set_aside is None and not cache.warm and [p.name for p in tmp_path.iterdir()] == [cache.key]
    _compile(cache)
    (cache.folder / RECORD_FILE).unlink()  # files an unfinished warm-up left (a crash before its record)
    with pytest.raises(RuntimeError, match="set aside as"), cache.compiling() as warm:
        assert not warm
        raise ValueError("bad graph")
    assert cache.set_aside is not None and _contents(cache.set_aside / "inductor")["bf/cbf.py"] == COMPILED["bf/cbf.py"]
    assert _compile(cache) is False and cache.warm


def test_a_damaged_folder_that_cannot_be_set_aside_is_not_used(tmp_path, caplog, monkeypatch):
    cache = CompileCache(tmp_path, {"settings": 1})
    _compile(cache)
    (cache.folder / "inductor" / "bf" / "cbf.py").write_bytes(b"")
    damaged = _contents(cache.folder)

    def refuse(self):
        raise PermissionError(13, "Permission denied", str(self.folder))

    monkeypatch.setattr(CompileCache, "_set_folder_aside", refuse)
    with caplog.at_level(logging.WARNING, logger="hf_specvla"), cache.compiling() as warm:
        assert not warm and os.environ.get("TORCHINDUCTOR_CACHE_DIR") != str(cache.folder / "inductor")
    assert _contents(cache.folder) == damaged  # neither used nor recorded again
    assert "cannot be set aside" in caplog.text and "compiles without the compile cache" in caplog.text


@pytest.fixture(scope="module")
def cold_folder(tmp_path_factory) -> Path:
    """A compile cache that a real compile (a fresh process's cold start) recorded; copied by each test."""
    root = tmp_path_factory.mktemp("cold") / "cache"
    first, _ = _start(root, "damaged", root.parent / "default")
    assert first["warm"] is False and first["misses"] == 1
    return root


def _graph_module(folder: Path) -> Path:
    """The Python module of the compiled graph in a key's folder, the file Inductor imports (one: START's graph)."""
    (module,) = folder.glob("inductor/*/*.py")
    return module


@pytest.mark.commands  # ~30 s: two fresh processes (the shared cold start, one more compiling)
def test_a_real_compile_whose_graph_file_was_emptied_starts_cold_not_crashing_and_warms_again(tmp_path, cold_folder):
    root = tmp_path / "cache"
    shutil.copytree(cold_folder, root)
    (folder,) = root.iterdir()
    _graph_module(folder).write_bytes(b"")  # the probe's damage: Inductor's "has no attribute 'call'" on every start
    second, log = _start(root, "damaged", tmp_path / "default2")
    assert (second["warm"], second["hits"], second["misses"], second["equal"]) == (False, 0, 1, True)
    (aside,) = root.glob(f"*{DAMAGED}*")
    assert aside.name.startswith(f"{folder.name}{DAMAGED}") and _graph_module(aside).stat().st_size == 0
    assert f"{folder} is damaged, inductor/" in log and f"set aside as {aside}" in log
    assert _graph_module(folder).stat().st_size > 0  # compiled again
    assert CompileCache(root, json.loads((folder / RECORD_FILE).read_text())).warm  # the next start is warm


@pytest.mark.commands  # ~20 s: two fresh processes (one failing, one compiling) after the shared cold start
def test_a_real_compile_that_fails_on_a_damaged_graph_the_check_missed_names_the_folder_and_the_next_start_heals(
    tmp_path, cold_folder
):
    root = tmp_path / "cache"
    shutil.copytree(cold_folder, root)
    (folder,) = root.iterdir()
    module = _graph_module(folder)
    module.write_bytes(module.read_bytes()[: module.stat().st_size // 2])  # truncated, and its list of files says
    CompileCache(root, json.loads((folder / RECORD_FILE).read_text()))._record_files()  # so: the check passes
    _, log = _start(root, "damaged", tmp_path / "default2", fails=True)
    (aside,) = root.glob(f"*{DAMAGED}*")
    assert f"RuntimeError: compile cache {root}: a start from the compiled files in {folder} failed" in log
    assert f"set aside as {aside}: the next start compiles cold" in log and "SyntaxError" in log
    third, _ = _start(root, "damaged", tmp_path / "default3")
    assert (third["warm"], third["misses"], third["equal"]) == (False, 1, True)


def test_the_service_says_in_its_startup_where_it_set_a_damaged_folder_aside(tmp_path, caplog, monkeypatch):
    from hf_specvla.policies import VLAPolicy

    policy = VLAPolicy.from_pretrained(POLICY)
    service = PolicyService(policy, ServeConfig(method="exact", buckets=(1,), calibration_calls=0,
                                                compile_cache=str(tmp_path)))  # fmt: skip

    def warm_up(calibrate, seed):  # the compile's files without the compile (fast): the cache's part alone
        service.startup.update(compile_s=0.0, calibrate_s=0.0)
        if service.startup["compile_cache"] == "cold":
            (Path(service.startup["compile_cache_folder"]) / "inductor" / "graph.py").write_text("def call(): ...")
        return []

    monkeypatch.setattr(service, "_warm_up", warm_up)
    try:
        service.warm_up()
        folder = Path(service.startup["compile_cache_folder"])
        assert service.startup["compile_cache"] == "cold" and "compile_cache_set_aside" not in service.startup
        (folder / "inductor" / "graph.py").write_bytes(b"")
        with caplog.at_level(logging.WARNING, logger="hf_specvla"):
            service.warm_up()
        startup = service.info()["startup"]
        aside = Path(startup["compile_cache_set_aside"])
        assert startup["compile_cache"] == "cold" and aside.name.startswith(f"{folder.name}{DAMAGED}")
        assert f"{folder} is damaged, inductor/graph.py has 0 bytes" in caplog.text
        service.warm_up()
        assert service.startup["compile_cache"] == "warm" and "compile_cache_set_aside" not in service.startup
    finally:
        service.close()
