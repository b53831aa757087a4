"""Process-wide numeric settings (core/threads.py): BLAS pools and numpy's huge-page advice."""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys

import pytest
from hapticloud.core import threads


def _child_advice_after_settle(conn) -> None:  # type: ignore[no-untyped-def]
    threads.settle_numerics(1)
    # The setter returns the previous value: what settle_numerics left.
    conn.send(threads.numpy_hugepages(False))


@pytest.fixture
def restore_advice():
    before = threads.numpy_hugepages(False)
    yield
    threads.numpy_hugepages(before)


def test_set_environment_turns_the_advice_off_but_respects_the_user(monkeypatch) -> None:
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    threads.set_environment(1)
    assert os.environ["NUMPY_MADVISE_HUGEPAGE"] == "0"
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    threads.set_environment(1)
    assert os.environ["NUMPY_MADVISE_HUGEPAGE"] == "1"


def test_numpy_hugepages_sets_and_reports(monkeypatch, restore_advice) -> None:
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    threads.numpy_hugepages(True)
    assert threads.numpy_hugepages(False) is True
    assert threads.numpy_hugepages(False) is False
    # The user's explicit "1" wins over hapticloud's default.
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    threads.numpy_hugepages(False)
    assert threads.numpy_hugepages(True) is True


def test_a_spawned_child_runs_without_the_advice(monkeypatch) -> None:
    # A child that did not inherit the variable (a library user's process, not the CLI's):
    # settle_numerics, which every hapticloud child calls first, still turns the advice off.
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child_advice_after_settle, args=(send,))
    proc.start()
    try:
        assert recv.poll(60.0)
        assert recv.recv() is False
    finally:
        proc.join(10.0)


def test_the_command_line_sets_it_before_numpy_is_imported() -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    code = (
        "import hapticloud.app.cli, numpy, sys; "
        "from hapticloud.core.threads import numpy_hugepages; "
        "sys.stdout.write(str(numpy_hugepages(False)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout == "False"
