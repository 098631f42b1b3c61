"""The suite-wide guard (conftest._guarded): a failing call that changes a named file is caught."""

import pytest

from keyshape.cli import main

from conftest import _guarded


def test_every_in_process_call_is_guarded():
    assert hasattr(main, "__wrapped__")


def test_a_failing_call_that_changes_an_input_is_caught(tmp_path):
    victim = tmp_path / "take.npz"
    victim.write_bytes(b"before")

    def spoils(argv):
        victim.write_bytes(b"after")
        return 1

    with pytest.raises(AssertionError, match=r"failed .* and changed"):
        _guarded(spoils)(["solve", str(victim), "-o", str(tmp_path / "w.csv")])


def test_a_folder_named_counts_and_a_success_may_write(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "keys.json").write_text("{}")

    def rewrites(argv):
        (folder / "keys.json").write_text("[]")
        return 0

    assert _guarded(rewrites)(["run", "clip.mp4", "-o", str(folder)]) == 0  # success: outputs are written

    def spoils(argv):
        (folder / "keys.json").write_text("spoilt")
        raise SystemExit(2)

    with pytest.raises(AssertionError, match="exit 2"):
        _guarded(spoils)(["run", "clip.mp4", "-o", str(folder)])
