"""`keyshape coverage`, `keys --extend` and `rom` on a real take: the embedded clip's halves."""

import json

import pytest

from keyshape.capture.rom import ROM_SCRIPT, rom_duration
from keyshape.cli import main
from keyshape.io import load_keys, load_track, save_track

from conftest import read_frames, write_video

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def halves(demo_out, tmp_path_factory):
    """The demo take cut in two, and the key set of its first half."""
    folder = tmp_path_factory.mktemp("halves")
    track = load_track(demo_out / "track.npz")
    first, second = save_track(track[:236], folder / "first.npz"), save_track(track[236:], folder / "second.npz")
    assert main(["keys", str(first), "-o", str(folder / "keys.json"), "-q"]) == 0
    return folder, first, second


def test_coverage_of_a_new_take(halves, capsys):
    folder, _, second = halves
    out = folder / "cov"
    assert main(["coverage", str(second), "--keys", str(folder / "keys.json"), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "coverage.json").read_text())
    assert report["take"] == "second.npz" and set(report["regions"]) == {"upper", "lower"}
    lower = report["regions"]["lower"]
    far = report["frames_out_of_reach"]["lower"]
    assert lower["frames_out_of_reach"] == len(far) > 0  # the second half shows mouth moves the first lacks
    curve = lower["error_vs_added_keys"]
    assert curve[0] == pytest.approx(lower["rms_error"], rel=1e-3) and curve[-1] < report["max_error"] < curve[0]
    need = lower["keys_to_add"]
    assert need >= 1 and curve[need] < report["max_error"] <= curve[need - 1]
    assert len(curve) >= need + 4  # the curve runs three keys past the target
    assert "lower: RMS error" in printed and "out of reach" in printed
    png = (out / "coverage.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_extend_keeps_every_old_key_and_reaches_the_take(halves, capsys):
    folder, _, second = halves
    extended = folder / "extended.json"
    assert main(["keys", str(second), "--extend", str(folder / "keys.json"), "-o", str(extended)]) == 0
    assert "to sculpt:" in capsys.readouterr().out
    old_json, new_json = json.loads((folder / "keys.json").read_text()), json.loads(extended.read_text())
    old, new = load_keys(folder / "keys.json"), load_keys(extended)
    for name in old.names:  # name, shape and source kept as they were
        assert new_json["shapes"][name] == old_json["shapes"][name]
        j, k = new.names.index(name), old.names.index(name)
        assert (new.frames[j], new.takes[j], new.key_regions[j], new.mirror_of[j]) == \
               (old.frames[k], old.takes[k], old.key_regions[k], old.mirror_of[k])
    added = [n for n in new.names if n not in old.names]
    assert added and all(new.takes[new.names.index(n)] == "second.npz" for n in added if not
                         new.mirror_of[new.names.index(n)])
    cov = folder / "cov2"
    assert main(["coverage", str(second), "--keys", str(extended), "-o", str(cov), "-q"]) == 0
    after = json.loads((cov / "coverage.json").read_text())
    for row in after["regions"].values():
        assert row["rms_error"] < after["max_error"] and row["keys_to_add"] == 0


def test_extend_refuses_to_overwrite_the_key_set_it_extends(halves):
    folder, _, second = halves
    keys = folder / "keys.json"
    original = keys.read_bytes()
    assert main(["keys", str(second), "--extend", str(keys), "-o", str(keys), "-q"]) == 2
    assert keys.read_bytes() == original


def test_the_rom_script_covers_each_part_and_each_side(capsys):
    assert 18 <= len(ROM_SCRIPT) <= 30 and 40 < rom_duration() < 150
    covered = " ".join(step.covers for step in ROM_SCRIPT)
    for part in ("brows", "lids", "cheeks", "nose", "jaw", "lips"):
        assert part in covered
    names = [step.name for step in ROM_SCRIPT]
    for one_sided in ("brow_up", "wink", "smile", "jaw", "mouth"):
        assert f"{one_sided}_left" in names and f"{one_sided}_right" in names
    assert main(["rom"]) == 0
    printed = capsys.readouterr().out
    assert all(step.say in printed for step in ROM_SCRIPT) and "keyshape keys rom.mp4" in printed
    assert main(["rom", "--json"]) == 0
    assert [s["name"] for s in json.loads(capsys.readouterr().out)["steps"]] == names


def test_keys_builds_one_set_from_a_rom_video_and_a_take(demo_clip, halves, tmp_path):
    """A video among the takes is tracked first (here a short stretch of the real clip plays the ROM)."""
    _, first, _ = halves
    rom = write_video(tmp_path / "rom.mp4", read_frames(demo_clip, 60))
    out = tmp_path / "k.json"
    assert main(["keys", str(rom), str(first), "-o", str(out), "-q", "--count", "4"]) == 0
    keys = load_keys(out)
    assert set(keys.takes) <= {"rom.mp4", "first.npz"} and "first.npz" in keys.takes
    assert keys.neutral_take == "rom.mp4"
