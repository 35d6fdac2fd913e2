"""Input and output paths that are not what they look like are named for what they are: a
directory named like a tile, a FIFO, a device, a broken symbolic link as --out."""

import os
from pathlib import Path

import pytest

from pipeline.errors import InputError
from workflows.config.inputs import expand_inputs
from workflows.run.directory import OutputError, prepare_output
from tests.workflows.conftest import error_line, silva, write_config


@pytest.fixture
def odd(tmp_path) -> Path:
    """A directory holding a tile-named directory, a FIFO, a link to /dev/zero and a file."""
    folder = tmp_path / "in"
    (folder / "t.laz").mkdir(parents=True)
    os.mkfifo(folder / "f.laz")
    (folder / "z.laz").symlink_to("/dev/zero")
    (folder / "real.laz").write_bytes(b"")
    return folder


def test_a_directory_named_like_a_tile(odd):
    with pytest.raises(InputError, match=r"t\.laz' in data\.train is a directory, not a "
                                         r"LAS/LAZ file; give its files"):
        expand_inputs([odd / "t.laz"], key="data.train")


def test_a_glob_that_matches_only_directories(odd):
    with pytest.raises(InputError, match=r"matches only directories, not LAS/LAZ files "
                                         r"\(.*t\.laz\)"):
        expand_inputs([str(odd / "t*")], key="data.train")


@pytest.mark.parametrize("name, kind", [("f.laz", "a named pipe (FIFO)"),
                                        ("z.laz", "a character device (/dev/zero)")])
def test_a_path_that_is_no_regular_file(odd, name, kind):
    with pytest.raises(InputError) as caught:
        expand_inputs([odd / name], key="data.test")
    assert f"{name}' in data.test is {kind}, not a regular file" in str(caught.value)


def test_dev_zero_itself():
    with pytest.raises(InputError, match="'/dev/zero' is a character device, not a regular"):
        expand_inputs(["/dev/zero"])


@pytest.mark.parametrize("pattern, name", [("f*.laz", "f.laz"), ("z*", "z.laz")])
def test_a_glob_that_matches_a_fifo_or_device(odd, pattern, name):
    with pytest.raises(InputError, match=rf"{name}' \(matched by .* in data.train\) is a .*, "
                                         "not a regular file; remove it or narrow the glob"):
        expand_inputs([str(odd / pattern)], key="data.train")


def test_directories_among_files_of_a_glob_are_skipped(odd):
    os.unlink(odd / "f.laz")
    os.unlink(odd / "z.laz")
    assert expand_inputs([str(odd / "*.laz")]) == [odd / "real.laz"]


def test_the_cli_names_the_fifo_without_blocking(odd, tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(f"data:\n  train: ['{odd / 'f.laz'}']\n  classes: {{tree: [5]}}\n")
    line = error_line(silva("plan", config))
    assert "f.laz' in data.train is a named pipe (FIFO), not a regular file" in line


# -- --out through a broken symbolic link ----------------------------------------------
@pytest.mark.parametrize("below", [False, True])
def test_out_that_is_a_broken_symbolic_link(tmp_path, below):
    link = tmp_path / "results"
    link.symlink_to(tmp_path / "gone" / "results")
    out = link / "run1" if below else link
    with pytest.raises(OutputError) as caught:
        prepare_output(out, overwrite=False)
    message = str(caught.value)
    assert f"{link} is a broken symbolic link (to {tmp_path / 'gone' / 'results'})" in message
    assert "remove it or choose another --out" in message and "File exists" not in message
    assert link.is_symlink() and not (tmp_path / "gone").exists()


def test_out_through_a_working_symbolic_link_is_used(tmp_path):
    (tmp_path / "real").mkdir()
    link = tmp_path / "results"
    link.symlink_to(tmp_path / "real")
    with prepare_output(link / "run1", overwrite=False):
        assert (tmp_path / "real" / "run1").is_dir()


def test_run_with_a_broken_link_as_out(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    (tmp_path / "out").symlink_to(tmp_path / "nowhere")
    line = error_line(silva("run", config, "--out", tmp_path / "out", "--in-process", "-q"))
    assert "is a broken symbolic link" in line and "remove it or choose another --out" in line


# -- a header that gives no real coordinates -------------------------------------------
@pytest.mark.parametrize("command", ["plan", "ingest"])
def test_a_nan_scale_is_refused_before_any_chunk(tmp_path, survey, command):
    import struct

    tile = sorted(survey["train"].glob("*.laz"))[0]
    data = bytearray(tile.read_bytes())
    data[139:147] = struct.pack("<d", float("nan"))  # the header's y scale
    bad = tmp_path / "bad.laz"
    bad.write_bytes(bytes(data))
    config = write_config(tmp_path / "c.yaml", survey)
    out = ["--out", tmp_path / "out", "--in-process", "-q"] if command == "ingest" else []
    result = silva(command, config, "--set", f"data.train=[{bad}]", *out)
    line = error_line(result)
    assert f"{bad}: header y scale is nan;" in line
    assert "chunk" not in result.output and "RuntimeWarning" not in result.output
    assert not (tmp_path / "out" / "store.zarr").exists()


# -- a wrong input path --------------------------------------------------------------------
def test_a_wrong_tile_path_leaves_no_output_directory(tmp_path):
    out = tmp_path / "out"
    line = error_line(silva("predict", "--model", "forest-tls-synthetic", "--out", out,
                            tmp_path / "nope.laz", "--in-process", "-q"))
    assert f"no file matches '{tmp_path / 'nope.laz'}' in data.predict" in line
    assert not out.exists()


def test_a_wrong_path_in_a_configuration_leaves_no_output_directory(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(f"data:\n  train: ['{tmp_path / 'missing' / '*.laz'}']\n"
                      "  classes: {tree: [5]}\n")
    out = tmp_path / "out"
    line = error_line(silva("train", config, "--out", out, "--in-process", "-q"))
    assert "in data.train" in line
    assert not out.exists()
