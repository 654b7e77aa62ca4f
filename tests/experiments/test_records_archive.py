"""Published results packed into one records archive per experiment folder, verified by
``summarize``; reading an archive never runs code nor writes a file."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile

import pytest

from tests.experiments.results_fixtures import known_explore, write_runs
from torchrl_recon.cli import main
from torchrl_recon.errors import DamagedFileError
from torchrl_recon.reports import summarize
from torchrl_recon.runs.archive import (
    ARCHIVE,
    MANIFEST,
    pack,
    read_members,
    run_records,
    sha256_bytes,
    verify_results,
)

RECORDS = {
    "drone/seed0/stages/models.json": b'{"wall_time_s": 1.0}',
    "drone/seed0/stages/setting_a/part_0.json": b'{"metrics": {}}',
    "drone/seed1/stages/models.json": b'{"wall_time_s": 2.0}',
}


def _published(tmp_path):
    """An experiment folder with five runs and a packed archive of their records."""
    folder = tmp_path / "explore"
    files = write_runs(folder, known_explore())
    results = {f.relative_to(folder).as_posix(): sha256_bytes(f.read_bytes()) for f in files}
    pack(folder, RECORDS, results)
    return folder, files


def _raw_archive(folder, members, manifest_members=None):
    """Write an archive by hand (tar members as given) and a manifest listing them."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:xz") as tar:
        for info, data in members:
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    (folder / ARCHIVE).write_bytes(buffer.getvalue())
    listed = manifest_members or {
        info.name: hashlib.sha256(data or b"").hexdigest() for info, data in members
    }
    (folder / MANIFEST).write_text(
        json.dumps({"archive": ARCHIVE, "members": listed, "results": {}})
    )


def _file(name, data=b"{}"):
    info = tarfile.TarInfo(name)
    info.size = len(data)
    return info, data


def test_members_read_back_in_memory_and_the_archive_is_reproducible(tmp_path):
    folder, _ = _published(tmp_path)
    assert read_members(folder) == RECORDS
    first = (folder / ARCHIVE).read_bytes()
    pack(folder, dict(reversed(list(RECORDS.items()))), {})
    assert (folder / ARCHIVE).read_bytes() == first  # same members, same bytes
    assert run_records(folder / "drone" / "seed0") == {
        "stages/models.json": b'{"wall_time_s": 1.0}',
        "stages/setting_a/part_0.json": b'{"metrics": {}}',
    }
    assert run_records(tmp_path) == {}  # no archive above: nothing
    assert sorted(p.name for p in folder.iterdir()) == sorted(["drone", MANIFEST, ARCHIVE])


def test_summarize_verifies_the_archive_and_the_results_hashes(tmp_path, capsys):
    folder, files = _published(tmp_path)
    summary = summarize([folder / "drone"])
    assert summary["archives"] == [
        {"archive": (folder / ARCHIVE).as_posix(), "members": 3, "results": 5}
    ]
    assert main(["summarize", str(folder)]) == 0
    assert (
        f"verified: 5 results.json and 3 records of {folder / ARCHIVE}" in capsys.readouterr().out
    )

    files[3].write_text(files[3].read_text().replace('"seed": 3', '"seed": 3 '))
    assert main(["summarize", str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{files[3]} does not match the SHA-256 recorded in" in err[0]


def test_a_results_file_the_manifest_does_not_list_is_named(tmp_path):
    folder, _ = _published(tmp_path)
    extra = write_runs(folder / "more", known_explore()[:1])[0]
    with pytest.raises(DamagedFileError, match=f"{extra} is not listed in .*publish_run.py"):
        verify_results([extra])
    assert verify_results([tmp_path / "elsewhere" / "results.json"]) == []  # not published


def test_a_changed_member_is_refused(tmp_path):
    folder, _ = _published(tmp_path)
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["members"]["drone/seed1/stages/models.json"] = "0" * 64
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(DamagedFileError, match="'drone/seed1/stages/models.json' does not match"):
        summarize([folder])


def test_a_truncated_archive_is_one_damaged_file_error(tmp_path):
    folder, _ = _published(tmp_path)
    data = (folder / ARCHIVE).read_bytes()
    (folder / ARCHIVE).write_bytes(data[: len(data) // 2])
    with pytest.raises(DamagedFileError, match="is not a readable tar.xz archive"):
        read_members(folder)


def _link(name, target, kind=tarfile.SYMTYPE):
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, target
    return info, None


@pytest.mark.parametrize(
    "members, words",
    [
        ([_file("/etc/passwd")], "not a plain relative path"),
        ([_file("../outside.json")], "not a plain relative path"),
        ([_file("a/../../outside.json")], "not a plain relative path"),
        ([_link("drone/link.json", "/etc/passwd")], "not a regular file"),
        ([_link("drone/hard.json", "drone/x.json", tarfile.LNKTYPE)], "not a regular file"),
        ([_file("drone/x.json"), _file("drone/x.json")], "is there twice"),
    ],
)
def test_unsafe_members_are_refused_and_nothing_is_written(tmp_path, members, words):
    folder = tmp_path / "explore"
    folder.mkdir()
    listed = {"drone/x.json": hashlib.sha256(b"{}").hexdigest()}
    _raw_archive(folder, members, listed)
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(DamagedFileError, match=words):
        read_members(folder)
    assert sorted(tmp_path.rglob("*")) == before


def test_members_the_manifest_does_not_list_or_lacks_are_refused(tmp_path):
    folder = tmp_path / "explore"
    folder.mkdir()
    _raw_archive(folder, [_file("drone/x.json")], {"drone/y.json": "0" * 64})
    with pytest.raises(DamagedFileError, match="'drone/x.json' is not in its manifest"):
        read_members(folder)
    _raw_archive(folder, [_file("drone/x.json")], {
        "drone/x.json": hashlib.sha256(b"{}").hexdigest(), "drone/y.json": "0" * 64
    })  # fmt: skip
    with pytest.raises(DamagedFileError, match="lacks 1 member"):
        read_members(folder)


def test_a_manifest_that_is_not_one_is_refused(tmp_path):
    folder, _ = _published(tmp_path)
    (folder / MANIFEST).write_text(json.dumps({"archive": ARCHIVE, "members": ["x"]}))
    with pytest.raises(DamagedFileError, match="is not a records manifest"):
        summarize([folder])
    (folder / MANIFEST).write_text(
        json.dumps({"archive": ARCHIVE, "members": {"/abs.json": "0" * 64}, "results": {}})
    )
    with pytest.raises(DamagedFileError, match="not a plain relative path"):
        read_members(folder)
