"""Bad command-line arguments of experiments/*.py and benchmarks/*.py: a one-line usage
error (exit status 2, naming the option) before any work, never a traceback; an option
given explicitly wins over ``--quick``'s preset; a stopped script names no ``--resume``.

The scripts' work is replaced by functions that raise :class:`Work`, so a check that is
missing fails the test at once instead of starting a simulation or a training run.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
from pathlib import Path

import pytest

import diffcontact

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # the benchmarks import common, train, ...
sys.path.insert(0, str(ROOT / "experiments"))  # compare imports reproduce


class Work(Exception):
    """Raised where a script would start its work."""


def _load(folder: str, name: str) -> types.ModuleType:
    """The script ``folder/name.py`` as a module of its own (experiments/control.py and
    benchmarks/control.py share a name; other tests register the experiments' by theirs)."""
    key = f"_script_{folder}_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, ROOT / folder / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module  # (dataclasses look their module up)
        spec.loader.exec_module(module)
    return sys.modules[key]


# where each script's work starts (replaced by a raise of Work)
WORK = {
    "chaos_floor": ["floor"],
    "cmr_mass_scale": ["fit_ratios"],
    "compare": ["job_pool"],
    "reproduce": ["job_pool"],
    "control": ["train_model", "plan_row"],
    "uncertainty": ["train_model"],
    "coulomb": ["run"],
    "solver": ["make_problems"],
    "simulate": ["time_case", "main_compare"],
    "train": ["time_task", "compare_dtypes", "extract_release", "_table"],
    "bench_control": ["time_case"],
    "backends": ["time_backend", "_compare"],
    "contact_models": ["contact_batch"],
    "threads": ["train_step_fn", "solver_fn", "_row"],
    "fastops": ["_sum_row"],
    "launches": ["simulate_row", "train_row"],
    "kernels": ["_kernels"],
    "profile_step": ["profile_task"],
    "chain": ["record_calls"],
    "warp_aot": ["compile_set"],
}
# scripts that write under --out: a folder of the test's unless the case gives one
WRITES = ("compare", "reproduce", "control", "uncertainty", "coulomb")


def _forbid_work(monkeypatch: pytest.MonkeyPatch, module: types.ModuleType, key: str) -> None:
    def work(*args, **kwargs):
        raise Work(f"{key}: work started")

    for name in WORK.get(key, ()):
        monkeypatch.setattr(module, name, work)
    if hasattr(module, "machine_header"):  # (it imports cvxpy, lightning, ... for versions)
        monkeypatch.setattr(module, "machine_header", lambda *a: [])
    monkeypatch.setattr(diffcontact, "load_system", work)  # rope_limits, velocity_jumps, ...


def _script(key: str) -> types.ModuleType:
    if key == "bench_control":
        return _load("benchmarks", "control")
    folder = "experiments" if (ROOT / "experiments" / f"{key}.py").is_file() else "benchmarks"
    return _load(folder, key)


def _run(module: types.ModuleType, argv: list[str]) -> int:
    try:
        return module.main(argv)
    except SystemExit as exc:
        return exc.code
    except KeyboardInterrupt:  # (pytest would stop the whole session)
        pytest.fail("KeyboardInterrupt escaped main()")


@pytest.fixture
def paths(tmp_path: Path) -> dict[str, str]:
    """``{file}``: a file; ``{dir}``: a folder; ``{data}``: a dataset folder's metadata (five
    masses); ``{tmp}``: an empty folder."""
    (tmp_path / "a-file").write_text("x\n")
    (tmp_path / "a-dir").mkdir()
    data = tmp_path / "data"
    data.mkdir()
    config = {"name": "BP5-e", "masses": [0.1] * 5}
    (data / "metadata.json").write_text(json.dumps({"config": config}))
    return {
        "file": str(tmp_path / "a-file"),
        "dir": str(tmp_path / "a-dir"),
        "data": str(data),
        "tmp": str(tmp_path),
    }


# (script, arguments, what the error line names); all ended in a traceback, garbage or
# work before (see the commit that added this file)
BAD = [
    ("chaos_floor", ["{data}", "--body", "-1"], "--body"),
    ("chaos_floor", ["{data}", "--body", "9"], "--body 9"),
    ("chaos_floor", ["{data}", "--rel", "nan"], "--rel"),
    ("chaos_floor", ["{data}", "--rel", "-2"], "--rel"),
    ("chaos_floor", ["{data}", "--rel", "inf"], "--rel"),
    ("cmr_mass_scale", ["{tmp}/none"], "data_dir"),
    ("cmr_mass_scale", ["{file}"], "data_dir"),
    ("cmr_mass_scale", ["{data}", "--chunks", "0"], "--chunks"),
    ("cmr_mass_scale", ["{data}", "--iters", "-1"], "--iters"),
    ("cmr_mass_scale", ["{data}", "--eps", "-1"], "--eps"),
    ("cmr_mass_scale", ["{data}", "--eps", "nan"], "--eps"),
    ("cmr_mass_scale", ["{data}", "--scales", "nan"], "--scales"),
    ("cmr_mass_scale", ["{data}", "--scales", "inf"], "--scales"),
    ("compare", ["models", "--out", "{file}", "--tasks", "BP5-e"], "--out"),
    ("compare", ["models", "--out", "{file}/sub"], "--out"),
    ("compare", ["models", "--n-train", "0"], "--n-train"),
    ("compare", ["models", "--n-val", "-1"], "--n-val"),
    ("compare", ["models", "--eval-steps", "0"], "--eval-steps"),
    ("compare", ["scalability", "--ds", "7"], "--ds"),
    ("compare", ["scalability", "--size-task", "Nope"], "--size-task"),
    ("compare", ["ablation", "--eps", "inf"], "--eps"),
    ("compare", ["noise", "--noise", "inf"], "--noise"),
    ("compare", ["models", "--quick"], "--quick"),
    ("compare", ["models", "--parts", "size"], "--parts"),
    ("compare", ["mismatch", "--models", "CM-CD-CLNN"], "--models"),
    ("compare", ["scalability", "--tasks", "Rope"], "--tasks"),
    ("reproduce", ["--only", "Nope:CM-CD-CLNN"], "--only"),
    ("reproduce", ["--only", "BP5:CM-CD-CLNN", "--tasks", "BP5"], "--only"),
    ("reproduce", ["--n-train", "0"], "--n-train"),
    ("reproduce", ["--out", "{file}"], "--out"),
    ("control", ["--out", "{file}", "--tasks", "throw"], "--out"),
    ("uncertainty", ["--out", "{file}"], "--out"),
    ("coulomb", ["--out", "{file}"], "--out"),
    ("coulomb", ["--mu", "-1"], "--mu"),
    ("coulomb", ["--mu", "nan"], "--mu"),
    ("coulomb", ["--cor", "2"], "--cor"),
    ("coulomb", ["--seed", "-1"], "--seed"),
    ("rope_limits", ["--task", "Nope"], "--task Nope"),
    ("rope_limits", ["--task", "BP5"], "--task BP5"),
    ("rope_limits", ["--task", "Rope", "--horizon", "0.02", "--dt", "0.01", "0.003"], "--dt"),
    ("rope_limits", ["--task", "Rope", "--tip-mass", "0"], "--tip-mass"),
    ("rope_limits", ["--task", "Rope", "--tip-mass", "nan"], "--tip-mass"),
    ("rope_limits", ["--task", "Rope", "--cor", "1.5"], "--cor"),
    ("projection_energy", ["--tasks", "Nope"], "--tasks Nope"),
    ("projection_energy", ["--cor", "-0.1"], "--cor"),
    ("projection_energy", ["--mu", "nan"], "--mu"),
    ("projection_energy", ["--n", "0"], "--n"),
    ("velocity_jumps", ["--n", "0"], "--n"),
    ("velocity_jumps", ["--seed", "-1"], "--seed"),
    ("solver", ["--contacts", "0"], "--contacts"),
    ("solver", ["--batches", "0"], "--batches"),
    ("solver", ["--budget", "-1"], "--budget"),
    ("solver", ["--budget", "nan"], "--budget"),
    ("solver", ["--cvx-tol", "-1"], "--cvx-tol"),
    ("solver", ["--json", "{dir}", "--no-baselines"], "--json"),
    ("solver", ["--seed", "-5"], "--seed"),
    ("simulate", ["--compare", "mujoco", "--n", "-1"], "--n"),
    ("simulate", ["--compare", "mujoco", "--steps", "0"], "--steps"),
    ("simulate", ["--compare", "mujoco", "--scenes", "8"], "--scenes"),
    ("simulate", ["--quick", "--all-tasks"], "--all-tasks"),
    ("simulate", ["--n", "4"], "--n"),
    ("train", ["--reps", "-1", "--against", "none"], "--reps"),
    ("train", ["--batch-size", "0"], "--batch-size"),
    ("train", ["--threads", "0"], "--threads"),
    ("train", ["--model", "Nope", "--against", "none"], "--model"),
    ("train", ["--tasks", "Nope", "--against", "none"], "--tasks"),
    ("train", ["--position-projection", "-1"], "--position-projection"),
    ("train", ["--compare-dtypes", "--mixed"], "--mixed"),
    ("train", ["--warp-block-dim", "0", "--against", "none"], "--warp-block-dim"),
    ("simulate", ["--warp-block-dim", "-32"], "--warp-block-dim"),
    ("warp_aot", ["--arch", "0"], "--arch"),
    ("warp_aot", ["--block-dims", "32", "0"], "--block-dims"),
    ("warp_aot", ["--sets", "16"], "--sets"),
    ("bench_control", ["--iterations", "0"], "--iterations"),
    ("bench_control", ["--iterations", "-1"], "--iterations"),
    ("backends", ["--batches", "0"], "--batches"),
    ("backends", ["--spatial-contacts", "0"], "--spatial-contacts"),
    ("backends", ["--threads", "-1"], "--threads"),
    ("backends", ["--seed", "-1"], "--seed"),
    ("contact_models", ["--n", "0"], "--n"),
    ("contact_models", ["--steps", "0"], "--steps"),
    ("contact_models", ["--repeats", "0"], "--repeats"),
    ("contact_models", ["--tasks", "Nope"], "--tasks"),
    ("threads", ["--task", "Nope"], "--task"),
    ("threads", ["--batch-size", "0"], "--batch-size"),
    ("threads", ["--reps", "-1"], "--reps"),
    ("threads", ["--steps", "0"], "--steps"),
    ("fastops", ["--device", "nope"], "--device"),
    ("fastops", ["--threads", "-1"], "--threads"),
    ("kernels", ["--sizes", "0"], "--sizes"),
    ("kernels", ["--sizes", "-2"], "--sizes"),
    ("kernels", ["--batch", "0"], "--batch"),
    ("profile_step", ["--rows", "-1"], "--rows"),
    ("chain", ["--scenes", "0"], "--scenes"),
    ("chain", ["--task", "Nope"], "--task"),
    ("chain", ["--scratch", "strided"], "--scratch"),
    ("chain", ["--device", "cpu", "--scratch", "diagonal"], "--scratch"),
    ("simulate", ["--warp-scratch", "diagonal"], "--warp-scratch"),
    ("rollout_growth", ["--rows", "-1"], "--rows"),
    ("rollout_growth", ["--quick", "--first", "9"], "--first"),
]


@pytest.mark.parametrize(
    ("key", "argv", "named"), BAD, ids=[f"{k}:{' '.join(a)}" for k, a, _ in BAD]
)
def test_bad_arguments_are_one_line_errors(key, argv, named, paths, monkeypatch, capsys):
    module = _script(key)
    _forbid_work(monkeypatch, module, key)
    argv = [a.format(**paths) for a in argv]
    if key in WRITES and "--out" not in argv:
        argv += ["--out", f"{paths['tmp']}/out"]
    if key in ("compare", "reproduce"):
        argv += ["--jobs", "1"]
    status = _run(module, argv)
    err = capsys.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert "error:" in last and named in last, last
    assert not Path(paths["tmp"], "out").exists()  # nothing written


def test_run_py_names_an_unknown_suite(capsys):
    run = _load("benchmarks", "run")
    assert run.main(["nope"]) == 2
    assert "unknown suite 'nope'" in capsys.readouterr().err


# ---------------------------------------------------------------- explicit options and --quick


class Stop(Exception):
    """Raised by a recording stand-in once it has what the test needs."""


def _record(seen: dict, *names: str):
    def stand_in(*args, **kwargs):
        seen.update(zip(names, args, strict=False))
        raise Stop

    return stand_in


def _settings_of(key: str, argv: list[str], monkeypatch, stand_ins: dict) -> None:
    module = _script(key)
    monkeypatch.setattr(module, "machine_header", lambda *a: [])
    for name, fn in stand_ins.items():
        monkeypatch.setattr(module, name, fn)
    with pytest.raises(Stop):
        module.main(argv)


def test_control_benchmark_quick_keeps_explicit_iterations(monkeypatch):
    seen: dict = {}
    stand_in = _record(seen, "task", "starts", "steps", "iterations")
    _settings_of("bench_control", ["--quick", "--iterations", "5"], monkeypatch,
                 {"time_case": stand_in})  # fmt: skip
    assert seen["steps"] == 20 and seen["iterations"] == 5
    _settings_of("bench_control", ["--quick"], monkeypatch, {"time_case": stand_in})
    assert seen["iterations"] == 2


def test_launches_quick_keeps_explicit_scenes(monkeypatch):
    seen: dict = {}
    _settings_of("launches", ["--quick", "--scenes", "8"], monkeypatch,
                 {"simulate_row": _record(seen, "scenes")})  # fmt: skip
    assert seen["scenes"] == 8


def test_kernels_quick_keeps_explicit_sizes(monkeypatch):
    seen: dict = {}

    def timed(wp, kernel, args, batch, reps):
        seen.update(n=args[-1], batch=batch, reps=reps)
        raise Stop

    fake_warp = types.SimpleNamespace(from_torch=lambda x: x)
    kernels = {"copy": 1, "C++": 2, "Warp": 3}
    _settings_of("kernels", ["--quick", "--sizes", "4", "--batch", "2"], monkeypatch,
                 {"_kernels": lambda: (fake_warp, kernels), "_time": timed})  # fmt: skip
    assert seen == {"n": 4, "batch": 2, "reps": 3}


def test_profile_step_quick_keeps_explicit_tasks_scenes_steps(monkeypatch):
    seen: dict = {}
    stand_in = _record(seen, "task", "scenes", "steps")
    argv = ["--quick", "--tasks", "BD5", "--scenes", "8", "--steps", "2"]
    _settings_of("profile_step", argv, monkeypatch, {"profile_task": stand_in})
    assert seen == {"task": "BD5", "scenes": 8, "steps": 2}
    _settings_of("profile_step", ["--quick", "--scenes", "8"], monkeypatch,
                 {"profile_task": stand_in})  # fmt: skip
    assert seen == {"task": "BP5", "scenes": 8, "steps": 3}


def test_chain_quick_keeps_explicit_task_scenes_steps(monkeypatch):
    seen: dict = {}
    stand_in = _record(seen, "task", "scenes", "steps")
    argv = ["--quick", "--task", "BD5", "--scenes", "8", "--steps", "2"]
    _settings_of("chain", argv, monkeypatch, {"record_calls": stand_in})
    assert seen == {"task": "BD5", "scenes": 8, "steps": 2}
    _settings_of("chain", ["--quick"], monkeypatch, {"record_calls": stand_in})
    assert seen == {"task": "BP5", "scenes": 256, "steps": 10}


def test_rollout_growth_quick_keeps_explicit_task_and_scenes(monkeypatch):
    seen: dict = {}

    def sample(scenes, **kwargs):
        seen["scenes"] = scenes
        raise Stop

    def load_system(task):
        seen["task"] = task
        return types.SimpleNamespace(default_steps=10, sample_initial_conditions=sample)

    module = _script("rollout_growth")
    monkeypatch.setattr(module, "dc", types.SimpleNamespace(load_system=load_system))
    _settings_of("rollout_growth", ["--quick", "--task", "Rope-D100", "--scenes", "8"],
                 monkeypatch, {})  # fmt: skip
    assert seen == {"task": "Rope-D100", "scenes": 8}


def test_threads_quick_keeps_explicit_steps_and_reps(monkeypatch):
    import diffcontact.threads

    seen: dict = {}

    def row(step, cores, reps, auto_steps, auto):
        seen.update(reps=reps, auto_steps=auto_steps)
        raise Stop

    monkeypatch.setattr(diffcontact.threads, "available_cores", lambda: 2)
    stand_ins = {"train_step_fn": lambda *a: None, "solver_fn": lambda *a: None,
                 "Rollout": lambda *a: None, "_row": row}  # fmt: skip
    _settings_of("threads", ["--quick", "--steps", "5", "--reps", "4"], monkeypatch, stand_ins)
    assert seen == {"reps": 4, "auto_steps": 5}
    _settings_of("threads", ["--quick"], monkeypatch, stand_ins)
    assert seen == {"reps": 3, "auto_steps": 24}


# ---------------------------------------------------------------- Ctrl-C and SIGTERM


def _interrupt(*args, **kwargs):
    from diffcontact.learning.training.options import TrainingInterrupted

    raise TrainingInterrupted(
        "SIGINT received: stopped before step 2 of 4 in epoch 1; wrote ck; continue with --resume",
        "SIGINT", 130, Path("run/checkpoints/last.ckpt"),
    )  # fmt: skip


STOPPED = [
    ("control", ["--tasks", "throw"], "train_model", "run the same command again"),
    ("uncertainty", ["--tasks", "BP5"], "train_model", "run the same command again"),
    ("coulomb", [], "run", "with a new --out"),
    ("compare", ["models", "--tasks", "BP5-e", "--models", "CM-CD-CLNN"], "make_dataset",
     "run the same command again"),
    ("reproduce", ["--only", "BP5:CM-CD-CLNN"], "make_dataset", "run the same command again"),
]  # fmt: skip


@pytest.mark.parametrize(("key", "argv", "where", "hint"), STOPPED, ids=[s[0] for s in STOPPED])
def test_a_stopped_script_names_no_resume_option(key, argv, where, hint, tmp_path,
                                                  monkeypatch, capsys):  # fmt: skip
    """``train()``'s TrainingInterrupted says "continue with --resume", an option of
    ``diffcontact train`` that these scripts do not have: they continue when run again."""
    module = _script(key)
    monkeypatch.setattr(module, where, _interrupt)
    status = _run(
        module,
        [
            *argv,
            "--out",
            str(tmp_path / "out"),
            *(["--jobs", "1"] if key in ("compare", "reproduce") else []),
        ],
    )
    err = capsys.readouterr().err
    assert status == 130, err
    last = err.strip().splitlines()[-1]
    assert "SIGINT received" in last and hint in last and "--resume" not in err, err
    assert "Traceback" not in err


# ---------------------------------------------------------------- the shared helpers


def test_check_writable_folder(tmp_path):
    from diffcontact.io import check_writable_folder

    (tmp_path / "f").write_text("x")
    assert check_writable_folder(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert check_writable_folder(tmp_path) == tmp_path
    assert not (tmp_path / "new").exists()  # a check: nothing made
    with pytest.raises(NotADirectoryError, match="exists and is not a folder"):
        check_writable_folder(tmp_path / "f")
    with pytest.raises(NotADirectoryError, match="is not a folder"):
        check_writable_folder(tmp_path / "f" / "sub")


def test_float_above():
    import argparse

    from diffcontact.cli_args import float_above

    parse = float_above(-1)
    assert parse("-0.5") == -0.5
    for text in ("-1", "nan", "inf", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_training_interrupted_survives_a_worker_process():
    """reproduce.py and compare.py run jobs in spawned processes, which pickle the stop back
    to the main one: unpickled from its message alone it raised TypeError, and the pool
    broke (BrokenProcessPool for every run) instead of the one-line stop."""
    import pickle

    from diffcontact.learning.training.options import TrainingInterrupted

    stop = TrainingInterrupted("SIGTERM received: stopped", "SIGTERM", 143, Path("ck"))
    back = pickle.loads(pickle.dumps(stop))
    assert isinstance(back, TrainingInterrupted) and str(back) == str(stop)
    assert (back.signal_name, back.exit_status, back.checkpoint) == ("SIGTERM", 143, Path("ck"))
