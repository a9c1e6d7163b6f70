"""The test's long-lived children write to a file: a child that writes more than a pipe holds never
blocks, and what it wrote is there for a failing assertion's message."""

import sys
import time

import pytest

from tests.processes import LoggedProcess


def test_logged_process__a_child_writing_megabytes_is_never_blocked():
    # 4 MiB, far above a pipe's 64 KiB: through an unread pipe this child would hang at 64 KiB
    child = LoggedProcess([sys.executable, "-c",
                           "import sys\nfor i in range(65536): print(f'line {i:05d} ' + 'x' * 52)\n"
                           "print('stderr too', file=sys.stderr)"])  # fmt: skip
    assert child.wait(30) == 0
    out = child.output()
    assert out.startswith("line 00000 ") and len(out) == 65536 * 64 + len("stderr too\n")
    assert out.endswith("stderr too\n")
    child.log_path.unlink()


def test_logged_process__a_running_childs_output_is_its_tail_so_far():
    child = LoggedProcess([sys.executable, "-c",
                           "import time\nprint('x' * 50_000 + 'END', flush=True)\ntime.sleep(60)"])  # fmt: skip
    try:
        for _ in range(200):
            if child.output().endswith("END\n"):
                break
            time.sleep(0.05)
        assert child.output(last=100) == "x" * 96 + "END\n"
    finally:
        child.kill()
        child.wait(10)


def test_logged_process__refuses_an_output_of_its_own():
    with pytest.raises(TypeError, match="stdout"):
        LoggedProcess([sys.executable, "-c", "pass"], stdout=None)
