"""``reeb_torch.runs.claim``: the one way a command takes its outputs. References: the files
and lock files on disk before and after, and a second claim made while the first holds."""

from __future__ import annotations

import click
from click.testing import CliRunner
import pytest

from reeb_torch.runs.claim import check_files, claim, claim_files
from reeb_torch.runs.common import UsageProblem


def test_a_second_claim_on_an_output_is_refused_until_the_first_lets_go(tmp_path):
    out = tmp_path / "w.safetensors"
    release = claim([out], hold=False)
    with pytest.raises(UsageProblem, match="another reeb run .* is writing this output"):
        claim([out], hold=False)
    release()
    release()  # twice is harmless
    claim([out], hold=False)()


def test_a_refused_claim_releases_what_it_took(tmp_path):
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    held = claim([second], hold=False)
    with pytest.raises(UsageProblem, match="--viz .*b.json"):
        claim([first, second], option="--viz", hold=False)
    claim([first], hold=False)()  # the lock of the first was given back
    held()


def test_a_claim_clears_what_a_killed_write_left_only_when_asked(tmp_path):
    out = tmp_path / "det.safetensors"
    left = tmp_path / ".det.safetensors.ab12cd34.tmp"
    other = tmp_path / ".other.safetensors.ab12cd34.tmp"
    for p in (left, other):
        p.write_bytes(b"partial")
    claim([out], hold=False)()
    assert left.exists()  # a run's killed rows: --resume goes on from them
    claim([out], hold=False, clear=True)()
    assert not left.exists() and other.exists()


def test_claims_made_in_a_command_are_held_until_it_ends(tmp_path):
    out = tmp_path / "x.json"

    @click.command()
    def cmd():
        claim([out])
        with pytest.raises(UsageProblem):
            claim([out], hold=False)

    assert CliRunner().invoke(cmd, []).exit_code == 0
    claim([out], hold=False)()  # released when the command ended


@pytest.mark.parametrize("case, reason", [
    ("empty", "-o/--out is empty"),
    ("folder", "is a folder; give a file name such as"),
    ("under a file", "is a file, not a folder"),
    ("an input", "is RESULTS, the file read; give another name"),
    ("there", "exists; add --overwrite to replace it"),
])
def test_files_are_checked_before_any_work(tmp_path, case, reason):
    there = tmp_path / "there.json"
    there.write_text("{}")
    path = {"empty": " ", "folder": tmp_path, "under a file": there / "x.json", "an input": there,
            "there": there}[case]
    with pytest.raises(UsageProblem, match=reason):
        check_files([path], overwrite=False, inputs={there: "RESULTS"} if case == "an input" else None)
    assert there.read_text() == "{}"


def test_overwrite_lets_files_be_replaced_and_missing_folders_are_made(tmp_path):
    there = tmp_path / "there.json"
    there.write_text("{}")
    new = tmp_path / "deep" / "er" / "new.json"
    paths, release = claim_files([there, new], overwrite=True, hold=False)
    assert paths == [there, new] and new.parent.is_dir() and not new.exists()
    release()
    with pytest.raises(UsageProblem, match=r"there.json exists; add --overwrite"):
        claim_files([there, new], overwrite=False, hold=False)


def test_a_folder_that_cannot_be_written_is_refused():
    with pytest.raises(UsageProblem, match="cannot write to the folder /proc"):
        check_files(["/proc/x.json"], overwrite=False)
