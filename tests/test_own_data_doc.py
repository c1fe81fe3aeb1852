"""Every code block of docs/own-data.md runs, in order, in an empty folder.

Python blocks share one namespace (as in one session); each line of a bash block
is a ``diffcontact`` command, run through ``diffcontact.cli.main`` and required to
exit 0. Blocks marked ``# needs mujoco`` run when MuJoCo is installed. The text
block after ``<!-- printed by the worked example's commands -->`` must be what the
worked example's commands print (durations aside).
"""

from __future__ import annotations

import importlib.util
import re
import shlex
from pathlib import Path

from diffcontact.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "own-data.md"


MARKER = "<!-- printed by the worked example's commands -->"
WALK = "diffcontact convert coordinates recording.npz"  # the worked example's first command


def _printed_in_doc() -> list[str]:
    text = DOC.read_text()
    m = re.search(re.escape(MARKER) + r"\n```text\n(.*?)```", text, re.S)
    assert m, "the worked example's output block is missing"
    return m.group(1).splitlines()


def _no_durations(line: str) -> str:
    return re.sub(r"in \d+(\.\d+)? s\b", "in ? s", line.rstrip())


def _blocks() -> list[tuple[str, str]]:
    text = DOC.read_text()
    return [
        (m.group(1), m.group(2)) for m in re.finditer(r"```(python|bash)\n(.*?)```", text, re.S)
    ]


def test_doc_has_blocks_of_every_converter():
    code = "\n".join(body for _, body in _blocks())
    for name in ("convert positions", "convert coordinates", "convert mujoco",
                 "trajectories_from_positions", "trajectories_from_coordinates",
                 "trajectories_from_mujoco", "trajectory_checks"):  # fmt: skip
        assert name in code, name


def test_own_data_doc_blocks_run(tmp_path, monkeypatch, capsys):
    has_mujoco = importlib.util.find_spec("mujoco") is not None
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "own_data_doc"}
    commands = 0
    walk_output: list[str] = []
    for lang, body in _blocks():
        if "# needs mujoco" in body and not has_mujoco:
            continue
        if lang == "python":
            exec(compile(body, str(DOC), "exec"), namespace)
            continue
        walk = WALK in body
        capsys.readouterr()
        for line in body.replace("\\\n", " ").splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            argv = shlex.split(line)
            assert argv[0] == "diffcontact", line
            status = main(argv[1:])
            assert status == 0, f"{line}: exit {status}\n{capsys.readouterr().err}"
            commands += 1
        if walk:
            walk_output = capsys.readouterr().out.splitlines()
    assert commands == (9 if has_mujoco else 7)
    assert (tmp_path / "data" / "balls" / "metadata.json").is_file()
    # the worked example: learned parameters and plots, and the output the doc shows
    printed = [_no_durations(line) for line in walk_output]
    assert [_no_durations(line) for line in _printed_in_doc()] == printed
    files = {p.name for p in (tmp_path / "eval" / "two_balls").iterdir()}
    assert {"metrics.json", "impacts.png", "rel_error.png", "training.png", "rollout.gif"} <= files
    if has_mujoco:
        assert (tmp_path / "data" / "pendulum" / "metadata.json").is_file()
