"""run_case on every golden fixture: bit for bit the committed expected outputs and what
the command-line tool (run in-process and as `python -m liquid_splat`) writes, for any
thread count."""

import subprocess
import sys

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES, bits_equal


def test_run_case_is_the_golden_output(golden):
    name, t, m, e, em = golden
    out, om = ls.run_case(t, m)
    bits_equal(out, e)
    assert om == em


def test_thread_count_does_not_change_bits(golden):
    name, t, m, e, _ = golden
    bits_equal(ls.run_case(t, m, threads=1)[0], e)
    bits_equal(ls.run_case(t, m, threads=3)[0], e)


def test_run_case_equals_the_cli(golden, tmp_path):
    name, t, m, e, _ = golden
    out_file = tmp_path / "out.safetensors"
    code = ls.cli("case", "run", str(CASES / f"{name}.input.safetensors"), str(out_file))
    assert code == 0
    bits_equal(ls.run_case(t, m)[0], ls.load(out_file)[0])


def test_python_dash_m_runs_the_tool(tmp_path):
    out_file = tmp_path / "out.safetensors"
    r = subprocess.run(
        [sys.executable, "-m", "liquid_splat", "--threads", "2", "case", "run",
         str(CASES / "loss_f64.input.safetensors"), str(out_file)],
        capture_output=True, text=True,
    )
    assert r.returncode == 0, r.stderr
    bits_equal(ls.load(out_file)[0], ls.load(CASES / "loss_f64.expected.safetensors")[0])
    r = subprocess.run([sys.executable, "-m", "liquid_splat", "case", "run", str(tmp_path / "nope"),
                        str(out_file)], capture_output=True, text=True)
    assert r.returncode == 2 and "nope" in r.stderr
    r = subprocess.run([sys.executable, "-m", "liquid_splat", "--version"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and ls.__version__ in r.stdout


def test_save_and_load_round_trip(tmp_path):
    t = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array(3.5),
         "c": np.array([1, -2], dtype=np.int32)}
    ls.save(tmp_path / "x.safetensors", t, {"stage": "loss", "k": 0.1, "flag": True})
    back, meta = ls.load(tmp_path / "x.safetensors")
    bits_equal(back, t)
    assert meta == {"stage": "loss", "k": "0.1", "flag": "true"}


def test_the_gil_is_released_during_the_computation():
    import threading
    import time

    rng = np.random.default_rng(0)
    gt = rng.random((3, 512, 512))
    case = {"image": gt + 0.1 * rng.standard_normal(gt.shape), "gt": gt}
    window = []

    def work():
        t0 = time.perf_counter()
        ls.run_case(case, {"stage": "loss"}, threads=1)
        window.extend([t0, time.perf_counter()])

    ticks = []
    worker = threading.Thread(target=work)
    worker.start()
    while worker.is_alive():          # pure Python: runs only while the GIL is free
        ticks.append(time.perf_counter())
    worker.join()
    t0, t1 = window
    inside = [t0] + [t for t in ticks if t0 < t < t1] + [t1]
    longest_stall = max(b - a for a, b in zip(inside, inside[1:]))
    # Held during the computation, the GIL would stop this loop for most of [t0, t1].
    assert t1 - t0 > 0.05 and longest_stall < 0.5 * (t1 - t0), (t1 - t0, longest_stall)


def test_the_console_script_runs_the_tool(tmp_path):
    import os
    import shutil

    exe = shutil.which("liquid-splat", path=os.path.dirname(sys.executable))
    assert exe is not None, "the package installs a `liquid-splat` console script"
    r = subprocess.run([exe, "case", "new", "loss", str(tmp_path / "c.safetensors"), "--seed", "3"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    t, m = ls.load(tmp_path / "c.safetensors")
    assert m["stage"] == "loss" and t["image"].shape == (3, 24, 32)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals and file names")
def test_the_console_entry_point_ends_like_the_native_tool(tmp_path):
    import errno
    import os
    import signal

    tool = [sys.executable, "-m", "liquid_splat"]
    # Ctrl-C ends a long run at once (the Rust code runs without the interpreter).
    p = subprocess.Popen(tool + ["--threads", "1", "train", "--scene", "swing", "--resolution", "16",
                                 "--frames", "2", "--init-points", "50", "--iterations", "100000000",
                                 "--out", str(tmp_path / "run")],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        assert p.stderr.readline().startswith(b"training")
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=20) == -signal.SIGINT
    finally:
        p.kill()
        p.wait()
        p.stderr.close()
    # A closed stdout ends it quietly (`liquid-splat case compare A B | head -1`).
    r, w = os.pipe()
    os.close(r)
    case = str(CASES / "loss_f32.expected.safetensors")
    q = subprocess.run(tool + ["case", "compare", case, case], stdout=w, stderr=subprocess.PIPE)
    os.close(w)
    assert q.returncode == -signal.SIGPIPE and q.stderr == b"", q.stderr.decode()
    # In-process, `ls.cli` raises BrokenPipeError there, as Python's print does (the
    # interpreter ignores SIGPIPE), without a panic message.
    r, w = os.pipe()
    os.close(r)
    code = ("import liquid_splat as ls, sys\n"
            "try:\n    ls.cli('case', 'compare', sys.argv[1], sys.argv[1])\n"
            "except BrokenPipeError as e:\n    sys.stderr.write(f'caught {e.errno} {e}')\n")
    q = subprocess.run([sys.executable, "-c", code, case], stdout=w, stderr=subprocess.PIPE)
    os.close(w)
    assert q.returncode == 0 and q.stderr.decode() == f"caught {errno.EPIPE} [Errno {errno.EPIPE}] Broken pipe: standard output was closed", q.stderr.decode()
    # Another write error (a full disk) is an OSError with its errno.
    if os.path.exists("/dev/full"):
        code = ("import liquid_splat as ls, sys\n"
                "try:\n    ls.cli('case', 'compare', sys.argv[1], sys.argv[1])\n"
                "except OSError as e:\n    sys.stderr.write(f'caught {type(e).__name__} {e.errno} {e}')\n")
        with open("/dev/full", "w") as full:
            q = subprocess.run([sys.executable, "-c", code, case], stdout=full, stderr=subprocess.PIPE)
        assert q.returncode == 0 and q.stderr.decode().startswith(f"caught OSError {errno.ENOSPC} [Errno {errno.ENOSPC}] cannot write the standard output"), q.stderr.decode()
    # A file name that is not UTF-8 is a usage error (exit 2) with a message.
    q = subprocess.run(tool + ["case", "run", b"x\xff.safetensors", str(tmp_path / "o")],
                       capture_output=True)
    assert q.returncode == 2 and b"not valid UTF-8" in q.stderr and b"Traceback" not in q.stderr, q.stderr
