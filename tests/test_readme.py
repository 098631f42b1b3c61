"""README's commands as written (issue 36): every `keyshape ...` it shows parses against its verb's
own arguments, the cheap ones run, the verb list names every verb, and its figures are the demo's."""

from __future__ import annotations

import itertools
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from keyshape.cli._main import VERBS, build_parser

README = Path(__file__).resolve().parents[1] / "README.md"
TEXT = README.read_text(encoding="utf-8")
BLOCKS = re.findall(r"```(\w*)\n(.*?)```", TEXT, re.S)


def _block_commands() -> list[str]:
    """Every `keyshape` line of README's shell blocks, comments cut."""
    lines = (line.split(" #")[0].strip() for lang, body in BLOCKS if lang == "bash" for line in body.splitlines())
    return [line for line in lines if line.startswith("keyshape ")]


def _inline_commands() -> list[str]:
    """Every inline `keyshape ...` of README's prose (outside the code blocks)."""
    prose = re.sub(r"```.*?```", "", TEXT, flags=re.S)
    return re.findall(r"`(keyshape [^`]+)`", prose)


COMMANDS = _block_commands() + [c for c in _inline_commands() if len(c.split()) > 2]
MENTIONS = [c for c in _inline_commands() if len(c.split()) == 2]  # "`keyshape sculpt` writes the kit"


def _variants(command: str) -> list[str]:
    """The command with each ``[optional part]`` left out and put in, every combination."""
    parts = re.split(r"(\[[^\]]*\])", command)
    optional = [i for i, part in enumerate(parts) if part.startswith("[")]
    out = []
    for keep in itertools.product((False, True), repeat=len(optional)):
        chosen = list(parts)
        for i, k in zip(optional, keep):
            chosen[i] = parts[i][1:-1] if k else ""
        out.append(" ".join("".join(chosen).split()))
    return out


def _parse(command: str):
    """``command`` through the verb's own parser and its usage checks; the argparse message if it fails."""
    words = shlex.split(command)[1:]
    assert words and words[0] in VERBS, f"`{command}`: {words[:1]} is not a keyshape verb"
    try:
        args = build_parser(words[0]).parse_args(words)
        if hasattr(args.module, "check"):
            args.module.check(args.parser, args)
    except SystemExit:
        return False
    return True


def test_the_first_two_code_blocks_are_the_two_commands():
    assert [body for _, body in BLOCKS[:2]] == ["bash setup.sh && keyshape demo\n", "python -m pytest\n"]


def test_readme_says_what_the_tool_is_for_right_after_the_two_commands():
    after = TEXT.split("python -m pytest\n```\n", 1)[1].lstrip()
    assert after.startswith("keyshape turns a video of an actor's face into animation of a character")


def test_the_readme_shows_many_commands():
    assert len(COMMANDS) >= 30
    assert "keyshape run take.mp4 --rig avatar.glb --auto-targets -o out/" in COMMANDS


@pytest.mark.parametrize("command", [v for c in COMMANDS for v in _variants(c)])
def test_every_readme_command_parses_as_written(command, capsys):
    assert _parse(command), capsys.readouterr().err


def test_every_verb_mentioned_is_a_verb():
    assert MENTIONS and all(m.split()[1] in VERBS for m in MENTIONS)


def test_the_verb_list_names_every_verb():
    listed = {c.split()[1] for c in _block_commands()}
    assert sorted(set(VERBS) - listed) == []


def test_the_live_sections_resolve_names_its_output():
    solves = [c for c in COMMANDS if c.startswith("keyshape solve session/")]
    assert solves == ["keyshape solve session/track.npz session/keys.json -o session/weights.csv"]


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *shlex.split(command)], cwd=cwd, capture_output=True,
                          text=True, timeout=600, check=False)


CHEAP = [  # those that need no video and no rig: run as README shows them, in a folder holding a take
    "keyshape keys take.npz -o keys.json",
    "keyshape solve take.npz keys.json -o weights.csv",
    "keyshape arkit take.npz -o take_livelink.csv",
    "keyshape rom",
    "keyshape blender-addon -o dist/",
    "keyshape solve session/track.npz session/keys.json -o session/weights.csv",
]


def test_the_cheap_commands_run_as_written(demo_out, tmp_path):
    shutil.copy(demo_out / "track.npz", tmp_path / "take.npz")
    (tmp_path / "session").mkdir()
    for name in ("track.npz", "keys.json"):  # what `keyshape live ... --record session/` writes
        shutil.copy(demo_out / name, tmp_path / "session" / name)
    for command in CHEAP:
        assert command in COMMANDS, f"README no longer shows `{command}`"
        result = _run(command, tmp_path)
        assert result.returncode == 0, (command, result.stderr)
    written = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert {"keys.json", "weights.csv", "take_livelink.csv", "session/weights.csv"} <= written
    assert any(w.startswith("dist/") and w.endswith(".zip") for w in written)


def test_the_neutrals_figures_are_the_reports(demo_out):
    report = (demo_out / "report.html").read_text(encoding="utf-8")
    median = float(re.search(r'"median_activation": ([0-9.]+)', report).group(1))
    activation = float(re.search(r'"activation": ([0-9.]+)', report).group(1))
    said = re.search(r"scores pick frame (\d+) \([0-9.]+ / [0-9.]+, total ([0-9.]+), against the take's "
                     r"median ([0-9.]+)\)", " ".join(TEXT.split()))
    assert said, "README no longer states the neutral's figures"
    frame = int(re.search(r'"frame": (\d+), "rule"', report).group(1))
    assert (int(said.group(1)), said.group(2), said.group(3)) == (frame, f"{activation:.2f}", f"{median:.2f}")


def test_the_arkit_path_has_its_own_section_before_the_details():
    headings = re.findall(r"^## (.+)$", TEXT, re.M)
    arkit = [h for h in headings if "ARKit" in h and "Ready Player Me" in h and "VRM" in h and "MetaHuman" in h]
    assert len(arkit) == 1
    assert headings.index(arkit[0]) < headings.index("The verbs")
    section = TEXT.split(f"## {arkit[0]}\n", 1)[1].split("\n## ", 1)[0]
    assert "keyshape run take.mp4 --rig avatar.glb --auto-targets -o out/" in section


def test_the_readme_says_where_setup_installs_and_offers_the_light_install():
    flat = " ".join(TEXT.split("\n## ", 1)[0].split())  # before the first section
    assert "`setup.sh` installs into the first `python` on your `PATH`" in flat
    assert "| `pip install -e .` |" in flat
    extras = re.findall(r'`pip install -e "\.\[([\w-]+)\]"` \| \S', flat)
    declared = tomllib.loads((README.parent / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert sorted(extras) == sorted(declared)  # each extra, and what it adds
