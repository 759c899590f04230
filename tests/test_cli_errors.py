"""Bad input on the command line ends in one line on stderr and exit code 2, never a traceback:
an output folder that is a file or cannot be written, a damaged checkpoint, a wrong --set
(named as --set, not as the case file), a fixed dt above a stability limit."""
import pytest
from conftest import CASES

from torchsph.__main__ import main

POIS = [str(CASES / "poiseuille_2d"), "--quiet", "--set", "scene.n_height=20"]


def one_line_error(capsys, argv, *parts):
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("torchsph: error: "), err
    for p in parts:
        assert p in err[0], err[0]
    return err[0]


def test_out_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(f)], "--out", "is a file")


def test_out_that_cannot_be_written(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")  # a folder below a file cannot be made, even by root
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(f / "sub")], "--out", "cannot write there")


def test_damaged_checkpoint(tmp_path, capsys):
    assert main(POIS + ["--steps", "3", "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    ck = tmp_path / "checkpoint.pt"
    raw = bytearray(ck.read_bytes())
    mid = len(raw) // 2
    raw[mid:mid + 64] = bytes(b ^ 0xFF for b in raw[mid:mid + 64])  # 64 bytes flipped
    ck.write_bytes(bytes(raw))
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(tmp_path), "--restart", str(ck)],
                   "--restart", "checkpoint")


def test_truncated_checkpoint(tmp_path, capsys):
    assert main(POIS + ["--steps", "3", "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    ck = tmp_path / "checkpoint.pt"
    ck.write_bytes(ck.read_bytes()[:1000])
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(tmp_path), "--restart", str(ck)], "--restart")


def test_checkpoint_that_is_not_one(tmp_path, capsys):
    ck = tmp_path / "checkpoint.pt"
    ck.write_text("not a checkpoint")
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(tmp_path), "--restart", str(ck)], "--restart")


@pytest.mark.parametrize("setting, parts", [
    ("numerics.cfl=-1", ["--set numerics.cfl=-1", "cfl"]),
    ("numerics.nope=1", ["--set numerics.nope=1", "unknown key"]),
    ("scene.n_height=ten", ["--set scene.n_height=ten", "n_height"]),
    ("scene", ["--set scene", "section.key=value"]),
])
def test_set_errors_name_set_not_the_case_file(tmp_path, capsys, setting, parts):
    line = one_line_error(capsys, [str(CASES / "poiseuille_2d"), "--quiet", "--steps", "2", "--out", str(tmp_path),
                                   "--set", setting], *parts)
    assert "case.toml" not in line


def test_refused_fixed_dt_is_bad_input(tmp_path, capsys):
    one_line_error(capsys, POIS + ["--steps", "2", "--out", str(tmp_path), "--set", "numerics.dt_s=1.0"],
                   "numerics.dt_s", "exceeds the", "allow_unstable_dt")


def test_threads_must_be_positive(tmp_path, capsys):
    one_line_error(capsys, POIS + ["--steps", "2", "--threads", "0", "--out", str(tmp_path)], "--threads 0", "> 0")
