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


def test_an_input_folder_counts_and_outputs_may_be_written(tmp_path):
    folder = tmp_path / "take"
    folder.mkdir()
    (folder / "keys.json").write_text("{}")
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.csv").write_text("old")

    def writes_its_output(argv):  # e.g. a batch with one failed take still writes its summary
        (out / "summary.csv").write_text("new")
        return 1

    assert _guarded(writes_its_output)(["batch", str(folder), "-o", str(out)]) == 1

    def spoils(argv):
        (folder / "keys.json").write_text("spoilt")
        raise SystemExit(2)

    with pytest.raises(AssertionError, match="exit 2"):
        _guarded(spoils)(["report", str(folder)])
