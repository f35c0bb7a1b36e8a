"""Root pytest configuration: ``--device`` selects where tensor tests run (default cpu; ``fake-cuda``: CUDA
emulated on the CPU by tests/fake_cuda.py, which fails the run on any device mix it finds)."""

from __future__ import annotations

import contextlib
import os

import pytest

os.environ.setdefault("UNCERTSPLAT_NO_PROGRESS", "1")
# a CI service's settings that make typer and rich write colour codes or cut help at their width (GitHub Actions sets
# GITHUB_ACTIONS, many pipelines FORCE_COLOR): the tests read plain text. Colour there is what a user asked for; the
# tests of it set these themselves. (Before typer or rich is imported; subprocesses inherit it.)
for _name in ("GITHUB_ACTIONS", "FORCE_COLOR", "PY_COLORS", "TTY_COMPATIBLE", "TTY_INTERACTIVE", "TERMINAL_WIDTH"):
    os.environ.pop(_name, None)
# OpenMP threads that spin while waiting make torch 10-20x slower when another process shares the
# 2 cores (seen with parallel test workers); passive waiting costs nothing on an idle machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

FAKE_CUDA = "fake-cuda"


def pytest_addoption(parser):
    parser.addoption("--device", action="store", default="cpu",
                     help=f"torch device for tests: cpu, cuda or {FAKE_CUDA} (CUDA emulated on the CPU: "
                          "tests/fake_cuda.py; any CPU/CUDA mix it finds fails the run)")


def pytest_configure(config):
    if config.getoption("--device") != FAKE_CUDA:
        return
    if config.getoption("numprocesses", default=None):
        # each xdist worker would keep its own findings, and a worker's exit status does not fail the run
        raise pytest.UsageError(f"--device {FAKE_CUDA} runs in one process: add -p no:xdist or -n 0")
    from tests.fake_cuda import fake_cuda

    # one emulator for the whole session, left at pytest_unconfigure; the ExitStack keeps it reversible
    config._fake_cuda_stack = stack = contextlib.ExitStack()
    config._fake_cuda = stack.enter_context(fake_cuda())


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item, nextitem):
    fake = getattr(item.config, "_fake_cuda", None)
    if fake is not None:
        fake.test = item.nodeid  # a finding names the test that first met it
    return (yield)


def pytest_sessionfinish(session, exitstatus):
    fake = getattr(session.config, "_fake_cuda", None)
    if fake is not None and fake.findings:
        session.config._fake_cuda_report = fake.report()
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    report = getattr(config, "_fake_cuda_report", None)
    if report is not None:
        terminalreporter.section("fake CUDA: code that would fail on a real GPU", sep="=", red=True)
        terminalreporter.line(report)
    elif getattr(config, "_fake_cuda", None) is not None:
        terminalreporter.line("fake CUDA: no CPU/CUDA mix found")


def pytest_unconfigure(config):
    stack = getattr(config, "_fake_cuda_stack", None)
    if stack is not None:
        stack.close()


@pytest.fixture(scope="session")
def device(request):
    import torch

    name = request.config.getoption("--device")
    if name == FAKE_CUDA:
        from tests.fake_cuda import FAKE_CUDA as fake_device

        return fake_device
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("--device cuda given but CUDA is not available")
    return torch.device(name)
