"""Faults while `fbspost compensate` writes: an unwritable directory, a full disk, a failed rename,
SIGINT and SIGTERM mid-run. Whatever happens, the input is byte-for-byte intact, no output or
temporary file remains, and the error is one line; in-place replacement is one atomic rename of
a complete, flushed file that keeps the input's permissions and owner."""
import errno
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from fbspost.cli import main
from fbspost.write import atomicfile

ROOT = Path(__file__).resolve().parent.parent
TUBE = ROOT / "tests" / "data" / "tube-marlin2.gcode"  # 8400 lines: about 3 s at 1 kHz
# A few moves, a retract and passthrough lines: compensated in a fraction of a second.
SHORT = (b"M83\r\nG1 X0 Y0 Z0.2 F6000\r\nM106 S128 ; fan\r\nG1 X20 Y10 E0.8 F3000\r\nG1 X20 Y20 E0.4\r\n"
         b"G1 E-0.8 F2400\r\nG4 P100\r\nG1 X5 Y5 F9000\r\nM107\r\n")


def compensate(*args):
    # (--no-verify: on Marlin's planner the original would be kept for this short program, so the
    # faults would strike a copy of it; the faults while writing are the point here)
    return CliRunner().invoke(main, ["compensate", "-m", "bedslinger-example", "-q", "--no-verify", *map(str, args)])


@pytest.fixture
def program(tmp_path):
    path = tmp_path / "part.gcode"
    path.write_bytes(SHORT)
    return path


@pytest.fixture(scope="module")
def expected(tmp_path_factory):
    """SHORT compensated without any fault: what a complete output is."""
    folder = tmp_path_factory.mktemp("expected")
    (folder / "part.gcode").write_bytes(SHORT)
    assert compensate(folder / "part.gcode", "-o", folder / "out.gcode").exit_code == 0
    return (folder / "out.gcode").read_bytes()


def assert_nothing_lost(result_code, stderr, program, original, status=1, words=""):
    """The exit status, one line on stderr (no traceback), the input intact and alone in its folder."""
    assert result_code == status, stderr
    assert stderr.count("\n") == 1 and stderr.startswith("error: ") and "Traceback" not in stderr, stderr
    assert words in stderr
    assert program.read_bytes() == original
    assert sorted(p.name for p in program.parent.iterdir()) == [program.name]


# ---- unwritable places -------------------------------------------------------------------------

@pytest.fixture
def unwritable_dir(tmp_path):
    """A directory no file can be created in, even by root (for whom permissions do not count,
    sysfs refuses new files)."""
    if os.geteuid() != 0:
        folder = tmp_path / "read-only"
        folder.mkdir(mode=0o555)
        yield folder
        folder.chmod(0o755)
        return
    try:
        os.close(tempfile.mkstemp(dir="/sys")[0])
    except PermissionError:
        yield Path("/sys")
        return
    pytest.skip("no directory refuses root here")


def test_unwritable_output_directory(program, unwritable_dir):
    target = unwritable_dir / "part.gcode"
    result = compensate(program, "-o", target)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT, words=f"error: {target}: cannot write: ")
    assert not target.exists()


def test_in_place_in_a_directory_that_refuses_new_files(program, monkeypatch):
    """In place, the temporary file goes beside the input: its directory refusing it (as a
    read-only directory does, for anyone but root) leaves the input as it was."""
    def refuse(path, *args):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(atomicfile.os, "open", refuse)
    result = compensate(program)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT,
                        words=f"error: {program}: cannot write: Permission denied")


def test_interrupt_as_the_temporary_file_is_made_leaves_none(program, monkeypatch):
    """Ctrl-C just after the temporary file came into being, before its maker returned: the file is
    removed all the same (it was left behind when tempfile.mkstemp made it)."""
    real_open = os.open

    def made_then_interrupted(path, flags, mode=0o777):
        os.close(real_open(path, flags, mode))
        raise KeyboardInterrupt

    monkeypatch.setattr(atomicfile.os, "open", made_then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomicfile.atomic_write(program, lambda f: f.write(b"new"))
    assert sorted(p.name for p in program.parent.iterdir()) == [program.name]
    assert program.read_bytes() == SHORT


def test_output_below_a_regular_file(program):
    target = program.parent / "part.gcode" / "out.gcode"
    result = compensate(program, "-o", target)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT, words=f"error: {target}: cannot write: ")


# ---- a full disk ---------------------------------------------------------------------------------

class _FullDisk:
    """A file object that takes ``room`` bytes, then fails as a full disk does."""

    def __init__(self, f, room):
        self.f, self.room = f, room

    def write(self, data):
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


@pytest.mark.parametrize("room", [0, 100, 4000])
def test_disk_full_mid_write(program, monkeypatch, expected, room):
    assert len(expected) > room  # the disk fills before the output is complete
    fdopen = os.fdopen
    monkeypatch.setattr(atomicfile.os, "fdopen", lambda fd, mode: _FullDisk(fdopen(fd, mode), room))
    result = compensate(program)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT,
                        words=f"error: {program}: cannot write: No space left on device")


def test_disk_full_at_flush(program, monkeypatch):
    """Network and copy-on-write filesystems may report the full disk only when the data is synced."""
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomicfile.os, "fsync", full)
    result = compensate(program)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT, words="No space left on device")


def test_rename_fails(program, monkeypatch):
    def busy(src, dst):
        raise OSError(errno.EBUSY, "Device or resource busy")

    monkeypatch.setattr(atomicfile.os, "replace", busy)
    result = compensate(program)
    assert_nothing_lost(result.exit_code, result.stderr, program, SHORT, words="Device or resource busy")


# ---- in-place replacement ------------------------------------------------------------------------

def test_in_place_is_one_rename_of_a_complete_synced_file(program, monkeypatch, expected):
    """Until the rename the input holds its own bytes; the file renamed over it already holds the
    whole output, synced to disk; rename(2) swaps them atomically, so no reader (or crash) ever
    sees the input missing or partial."""
    events = []
    fsync, replace = os.fsync, os.replace

    def synced(fd):
        events.append("fsync")
        fsync(fd)

    def renamed(src, dst):
        events.append("replace")
        assert Path(dst) == program and Path(src).parent == program.parent
        assert program.read_bytes() == SHORT and Path(src).read_bytes() == expected
        replace(src, dst)

    monkeypatch.setattr(atomicfile.os, "fsync", synced)
    monkeypatch.setattr(atomicfile.os, "replace", renamed)
    assert compensate(program).exit_code == 0
    assert events[:2] == ["fsync", "replace"]  # the data, then the rename (then the directory entry)
    assert program.read_bytes() == expected
    assert sorted(p.name for p in program.parent.iterdir()) == ["part.gcode"]


@pytest.mark.parametrize("mode", [0o600, 0o640, 0o664, 0o755, 0o2750])
def test_in_place_keeps_permissions(program, mode):
    os.chmod(program, mode)
    assert compensate(program).exit_code == 0
    assert program.stat().st_mode & 0o7777 == mode


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a file to another user")
def test_in_place_keeps_the_owner(program):
    """Run as root (a print server's service), the file stays its user's."""
    os.chown(program, 1234, 5678)
    assert compensate(program).exit_code == 0
    assert (program.stat().st_uid, program.stat().st_gid) == (1234, 5678)


def test_in_place_through_a_symlink_replaces_its_target(tmp_path, program, expected):
    """A link to the program (a slicer's export folder, say) stays a link; the program changes."""
    link = tmp_path / "link.gcode"
    link.symlink_to(program.name)
    assert compensate(link).exit_code == 0
    assert link.is_symlink() and program.read_bytes() == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.gcode", "part.gcode"]


# ---- signals -------------------------------------------------------------------------------------

def start(*args):
    return subprocess.Popen([sys.executable, "-m", "fbspost.cli", "compensate", *map(str, args),
                             "-m", "bedslinger-example", "-q"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def open_files(pid):
    """The paths of the files ``pid`` has open (those that stay open while looked at)."""
    folder, paths = f"/proc/{pid}/fd", []
    try:
        fds = os.listdir(folder)
    except FileNotFoundError:  # ended
        return []
    for fd in fds:
        try:
            paths.append(os.readlink(os.path.join(folder, fd)))
        except FileNotFoundError:  # closed meanwhile
            pass
    return paths


def output_bytes(folder) -> int | None:
    """The size of the output's temporary file in ``folder`` (None: there is none)."""
    for path in folder.iterdir():
        if path.name.endswith(".tmp"):
            try:
                return path.stat().st_size
            except FileNotFoundError:  # removed meanwhile
                return None
    return None


def stop_when(proc, condition, what: str) -> None:
    """Waits, however slow the machine, for ``condition()``, then stops the process (SIGSTOP) and
    checks that it still holds: the signal the test sends next then strikes in that state, and
    the process cannot finish first, however fast the machine."""
    deadline = time.monotonic() + 600
    while not condition():
        assert proc.poll() is None, f"ended before {what}"
        assert time.monotonic() < deadline, f"no {what} in 10 min"
        time.sleep(0.002)
    proc.send_signal(signal.SIGSTOP)
    assert proc.poll() is None and condition(), f"ended as {what} was seen"


def interrupt(proc, signum) -> str:
    """``signum`` to the stopped process, which then runs on to handle it; its stderr."""
    proc.send_signal(signum)
    proc.send_signal(signal.SIGCONT)
    return proc.communicate(timeout=600)[1]


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc to see the program read")
@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["SIGINT", "SIGTERM"])
@pytest.mark.slow
def test_signal_while_computing(tmp_path, signum, status):
    """The signal arrives while the program is read and compensated: the output's temporary file
    exists, nothing flushed to it yet, and the program is open (its flavor was detected before
    the temporary file was made: this is the pipeline's reading). (A signal that strikes as the
    file is made: test_interrupt_as_the_temporary_file_is_made_leaves_none.)"""
    program = tmp_path / "part.gcode"
    program.write_bytes(TUBE.read_bytes())
    proc = start(program, "-o", tmp_path / "out.gcode")
    stop_when(proc, lambda: output_bytes(tmp_path) == 0 and str(program) in open_files(proc.pid),
              "the program read into an empty temporary file")
    stderr = interrupt(proc, signum)
    assert_nothing_lost(proc.returncode, stderr, program, TUBE.read_bytes(), status=status, words="interrupted")


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["SIGINT", "SIGTERM"])
@pytest.mark.slow
def test_signal_while_writing_in_place(tmp_path, signum, status):
    """The signal arrives once the temporary file holds some output (G5 output: seconds of writing)."""
    program = tmp_path / "part.gcode"
    program.write_bytes(TUBE.read_bytes())
    proc = start(program, "--format", "g5")
    stop_when(proc, lambda: (output_bytes(tmp_path) or 0) > 0, "output written")
    stderr = interrupt(proc, signum)
    assert_nothing_lost(proc.returncode, stderr, program, TUBE.read_bytes(), status=status, words="interrupted")
