"""A run's CPU threads (torchsph/run/threads.py): the cores free when it starts, shared among the
processes of its launch; --threads and OMP_NUM_THREADS decide where given."""
import torch
from conftest import CASES

from torchsph.__main__ import main
from torchsph.run import threads


def test_free_threads_leave_the_busy_cores_and_share_the_rest():
    assert threads.free_threads(2, 0.0) == 2
    assert threads.free_threads(2, 0.9) == 1  # another run on one of two cores: one thread, not two
    assert threads.free_threads(2, 3.7) == 1  # at least one
    assert threads.free_threads(16, 2.2) == 14
    assert threads.free_threads(16, 2.2, processes=4) == 3  # four ranks on this machine
    assert threads.free_threads(2, 0.0, processes=2) == 1


def test_the_run_says_its_threads_and_why(tmp_path, capsys, monkeypatch):
    """(conftest puts torch's threads back after the test.)"""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(threads, "cores", lambda: 8)
    monkeypatch.setattr(threads.os, "getloadavg", lambda: (5.2, 0.0, 0.0))
    assert main([str(CASES / "conduction_1d"), "--estimate"]) == 0
    assert "on 1 process, 3 thread(s) per process (8 cores, load 5.2)" in capsys.readouterr().err
    assert torch.get_num_threads() == 3
    assert main([str(CASES / "conduction_1d"), "--estimate", "--threads", "1"]) == 0
    assert "1 thread(s) per process (--threads)" in capsys.readouterr().err
    assert torch.get_num_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    torch.set_num_threads(2)
    assert main([str(CASES / "conduction_1d"), "--estimate"]) == 0  # the environment decides: left as it is
    assert "2 thread(s) per process (OMP_NUM_THREADS)" in capsys.readouterr().err
