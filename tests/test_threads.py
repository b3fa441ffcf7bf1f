"""Threads per role (issue 40): the command-line roles size PyTorch's threads to the machine's
cores (a worker 1, a trainer all cores but one) unless ``--threads``, ``$TMRL_THREADS`` or
``$OMP_NUM_THREADS`` says otherwise; on two cores that is one thread each, as in the demo, instead
of PyTorch's default of a thread per core in every role."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tmrl.cli import main
from tmrl.errors import UserError
from tmrl.roles import THREADS_ENV, role_threads


@pytest.fixture
def no_thread_settings(monkeypatch):
    monkeypatch.delenv(THREADS_ENV, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)


@pytest.mark.parametrize("cores,trainer,worker", [(1, 1, 1), (2, 1, 1), (4, 3, 1), (16, 15, 1)])
def test_each_role_gets_its_share_of_the_cores(no_thread_settings, cores, trainer, worker):
    assert role_threads("trainer", cores) == (trainer, f"{cores} cores")
    assert role_threads("worker", cores) == (worker, f"{cores} cores")


def test_tmrl_threads_then_omp_num_threads_override_the_share(no_thread_settings, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert role_threads("trainer", 16) == (3, "OMP_NUM_THREADS")
    monkeypatch.setenv(THREADS_ENV, "2")
    assert role_threads("worker", 16) == (2, THREADS_ENV)
    for bad in ("0", "two", "-1", "1.5"):
        monkeypatch.setenv(THREADS_ENV, bad)
        with pytest.raises(UserError, match="TMRL_THREADS"):
            role_threads("trainer", 16)


def test_size_threads_sets_torch_and_the_environment_in_a_fresh_process(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", THREADS_ENV)}
    code = ("import os, torch; from tmrl.roles import _cores, size_threads; n = size_threads('trainer'); "
            "print(n, torch.get_num_threads(), os.environ['OMP_NUM_THREADS'], os.environ['MKL_NUM_THREADS'], _cores())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, timeout=120)
    n, torch_threads, omp, mkl, cores = map(int, out.stdout.split())
    assert n == torch_threads == omp == mkl == max(1, cores - 1)


@pytest.mark.parametrize("argv,message", [
    (["--server", "--threads", "2"], "--threads goes with --trainer"),
    (["--worker", "--threads", "0"], "--threads 0: give at least 1"),
])
def test_threads_option_mistakes_are_one_line(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_a_bad_tmrl_threads_stops_the_command_before_it_starts(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv(THREADS_ENV, "many")
    assert main(["--trainer"]) == 2
    assert "TMRL_THREADS='many': set it to a whole number" in capsys.readouterr().err
    assert not (tmp_path / "TmrlData").exists()  # nothing was created
