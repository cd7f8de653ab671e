#!/usr/bin/env python
"""Fault harness for issue 15: bad inputs and faults, each run as a user would run it.

Every case runs in a fresh temporary folder, as a subprocess (the ``episeg`` CLI
through ``python -m``, or a small ``python -c`` snippet for the API), in its own
session, with a timeout, and is classified as one of

    ok-result     exit 0 and the case's output checks pass
    ok-error      exit 1/2 (CLI) or ValueError/TypeError (API), ONE line, naming the
                  argument/file and what was expected (each case's regexes)
    refused       a clean one-line error where a result was expected (real files refused)
    bad-message   an error that is not one line, or does not name the argument / what was expected
    silent-wrong  exit 0 but a per-case check fails (accepted silently, wrong output)
    unbounded     time or memory grows without bound (a memory cap was hit, or a scaling check failed)
    leftover      files that should not be there (.partial, -shm, -wal, .tmp, ...) or processes
                  still alive after the run ended
    traceback     a Python traceback or a C++ stack dump in the output
    data-loss     an input file changed or disappeared (every input is hashed before and after)
    hang          the timeout passed
    crash         killed by a signal the harness did not send (segfault, abort, OOM kill)

Usage::

    python benchmarks/faults.py [--jobs 2] [--only REGEX] [--list] [--json out.json] [--workdir DIR] [--keep]

Exit status 0 when every case is ok-result or ok-error. Module paths are in PATHS below
(one table, to switch after a restructure).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import fnmatch
import gzip
import hashlib
import json
import os
import platform
import re
import shlex
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

# ======================================================================================
# Module paths: the ONLY place that names modules of episeg_cv ("module" or "module:attr").
# ======================================================================================
PATHS = {
    "cli": "episeg_cv.cli",                          # python -m <cli>; <cli>:main is the entry point
    "pkg": "episeg_cv",                              # TwoViewGeometry, SegmentMatcher, match_descriptors,
                                                     # load_calibration, save_calibration, undistort_points, ...
    "colmap": "episeg_cv.colmap",                    # match_model, load_poses, load_model
    "scenes": "episeg_cv.scenes",                    # make_pair, make_collection
    "read_matches": "episeg_cv.io:read_matches",
}
#: Shared data (real files that must be accepted).
DINO = Path(os.environ.get("EPISEG_DINO", Path(__file__).resolve().parents[2] / "shared" / "data" / "dinoSparseRing"))

OUTCOMES = ["ok-result", "ok-error", "refused", "bad-message", "unbounded", "silent-wrong", "leftover",
            "traceback", "data-loss", "hang", "crash"]
#: Worst first: the case's outcome is the worst of its findings.
SEVERITY = ["crash", "hang", "data-loss", "traceback", "silent-wrong", "leftover", "unbounded", "refused",
            "bad-message", "ok-error", "ok-result"]
BAD = set(SEVERITY) - {"ok-error", "ok-result"}

#: Files that must never remain after a run (in the case folder, recursively).
LEFTOVER_GLOBS = ("*.partial", "*.partial-*", "*-shm", "*-wal", "*-journal", "*.tmp", "*.tmp.*", "*.tmp.npz")

PY = os.environ.get("EPISEG_PYTHON", sys.executable)
HERE = Path(__file__).resolve().parent


# ======================================================================================
# Case description
# ======================================================================================
@dataclass
class Run:
    """One process (or ``copies`` identical processes at once) of a case."""

    argv: list | None = None          # CLI arguments after ``python -m <cli>``
    code: str | None = None           # API: body of a function; ``return`` a value
    expect: str = "error"             # result | error | either
    err: tuple = ()                   # regexes the error text must all match (case-insensitive)
    cats: tuple = ("value", "type")   # API exception categories that count as a clean error
    check: object = None              # (ctx, run_result) -> None or a reason (for exit 0)
    timeout: float = 60.0
    mem_gb: float | None = None       # RLIMIT_AS in the child
    slow: dict = field(default_factory=dict)  # {"module:attr.path": seconds}: sleep before each call
    signal: tuple | None = None       # (signum, trigger, to_group); trigger ("line", rx) | ("time", s) | ("file", glob)
    probe: object = None              # (ctx, popen) -> None or reason, called when the trigger fires
    post_signal_timeout: float = 20.0
    copies: int = 1
    env: dict = field(default_factory=dict)
    cwd: str = "."                    # relative to the case folder
    resource_case: bool = False       # MemoryError / cap / timeout count as "unbounded", not traceback/hang
    action: object = None             # instead of a process: a step (d, fix) -> None between runs


@dataclass
class Case:
    name: str
    group: str
    doc: str
    runs: list
    setup: object = None              # (d: Path, fix: Path) -> None
    mutable: tuple = ()               # globs (relative) of inputs that may change (database, cache)
    extra_inputs: tuple = ()          # absolute paths outside the case folder to hash
    leftovers: tuple = ()             # extra globs that must not exist afterwards
    post: object = None               # (ctx) -> list of (outcome, reason)
    exclusive: bool = False           # run alone (timing, heavy)


@dataclass
class RunResult:
    argv: list
    rc: int | None
    out: str
    err: str
    seconds: float
    signalled: int | None = None      # signal the harness sent
    fired: bool = False               # the trigger fired before the process ended
    timed_out: bool = False
    survivors: list = field(default_factory=list)
    probe: str | None = None


class Ctx:
    def __init__(self, d: Path, fix: Path):
        self.d, self.fix = d, fix
        self.results: list[RunResult] = []


# ======================================================================================
# Running processes
# ======================================================================================
WRAPPER = r'''
import os, sys, json, time, importlib
cfg = json.loads(os.environ.pop("EPISEG_FAULTS_CFG"))
if cfg.get("mem"):
    import resource
    resource.setrlimit(resource.RLIMIT_AS, (cfg["mem"], cfg["mem"]))
for spec, secs in cfg.get("slow", {}).items():
    mod, _, attr = spec.partition(":")
    obj = importlib.import_module(mod)
    *path, name = attr.split(".")
    for a in path:
        obj = getattr(obj, a)
    def _make(orig, secs):
        def slow(*a, **k):
            time.sleep(secs)
            return orig(*a, **k)
        return slow
    setattr(obj, name, _make(getattr(obj, name), secs))
if cfg.get("module"):
    import runpy
    sys.argv = [cfg["module"]] + cfg["argv"]
    runpy.run_module(cfg["module"], run_name="__main__", alter_sys=True)
else:
    exec(compile(cfg["code"], "<case>", "exec"), {"__name__": "__main__"})
'''

API_PRELUDE = r'''
import sys, json, importlib, warnings
import numpy as np
P = __PATHS__
def _imp(spec):
    mod, _, attr = spec.partition(":")
    m = importlib.import_module(mod)
    for a in filter(None, attr.split(".")):
        m = getattr(m, a)
    return m
ep = _imp(P["pkg"])
TwoViewGeometry, SegmentMatcher = ep.TwoViewGeometry, ep.SegmentMatcher
K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
I3 = np.eye(3)
T = np.array([-1.0, 0, 0])
S = (160, 120)
def geom(**kw):
    a = dict(K1=K, K2=K, R=I3, t=T, image_size1=S, image_size2=S)
    a.update(kw)
    return TwoViewGeometry(a.pop("K1"), a.pop("K2"), a.pop("R"), a.pop("t"), **a)
_rng = np.random.default_rng(0)
P1 = _rng.uniform([5, 5], [150, 110], (60, 2))
P2 = P1 + [-10.0, 0.0]                      # depth 10 for t = (-1, 0, 0), f = 100
D1 = _rng.random((60, 128), dtype=np.float32)
D2 = (D1 + 0.01 * _rng.random((60, 128), dtype=np.float32)).astype(np.float32)
B1 = _rng.integers(0, 256, (60, 32), dtype=np.uint8)
B2 = B1.copy()
def kps(P):
    import cv2
    return [cv2.KeyPoint(float(x), float(y), 5.0) for x, y in np.asarray(P).reshape(-1, 2)]
def rot(ax, ang):
    import cv2
    return cv2.Rodrigues(np.asarray(ax, float) * ang)[0]
def summ(x):
    if isinstance(x, np.ndarray):
        f = bool(np.all(np.isfinite(x))) if x.dtype.kind in "fc" else True
        return {"shape": list(x.shape), "dtype": str(x.dtype), "finite": f,
                "sum": float(np.nansum(x)) if x.dtype.kind in "biuf" and x.size else 0.0}
    if isinstance(x, dict):
        return {str(k): summ(v) for k, v in list(x.items())[:50]}
    if isinstance(x, (list, tuple)):
        if len(x) > 20:
            return {"len": len(x), "head": [summ(v) for v in x[:3]]}
        return [summ(v) for v in x]
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x if not isinstance(x, float) or x == x else "nan"
    if hasattr(x, "queryIdx"):
        return {"q": x.queryIdx, "t": x.trainIdx, "d": float(x.distance)}
    return {"type": type(x).__name__}
def _case():
__BODY__
try:
    _r = _case()
except Exception as e:
    cat = ("memory" if isinstance(e, MemoryError) else "value" if isinstance(e, ValueError) else
           "type" if isinstance(e, TypeError) else "os" if isinstance(e, OSError) else "other")
    if cat in ("other", "memory"):
        raise
    print("API-ERROR", cat, type(e).__name__, json.dumps(str(e)), file=sys.stderr, flush=True)
    sys.exit(1)
print("API-RESULT", json.dumps(summ(_r)), flush=True)
'''


def api_code(body: str) -> str:
    body = textwrap.indent(textwrap.dedent(body).strip("\n"), "    ")
    if "return" not in body:
        body = body.rstrip("\n").split("\n")
        body[-1] = "    return " + body[-1].strip()
        body = "\n".join(body)
    return API_PRELUDE.replace("__PATHS__", repr(PATHS)).replace("__BODY__", body)


def base_env(extra=None) -> dict:
    env = dict(os.environ)
    env.pop("EPISEG_FAULTS_CFG", None)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra or {})
    return env


def command(run: Run) -> tuple[list, dict]:
    """(argv, env) of a run."""
    env = base_env(run.env)
    cfg = {}
    if run.mem_gb:
        cfg["mem"] = int(run.mem_gb * 2 ** 30)
    if run.slow:
        cfg["slow"] = run.slow
    if run.code is not None:
        cfg["code"] = api_code(run.code)
        env["EPISEG_FAULTS_CFG"] = json.dumps(cfg)
        return [PY, "-c", WRAPPER], env
    if cfg:
        cfg.update(module=PATHS["cli"], argv=[str(a) for a in run.argv])
        env["EPISEG_FAULTS_CFG"] = json.dumps(cfg)
        return [PY, "-c", WRAPPER], env
    return [PY, "-m", PATHS["cli"], *[str(a) for a in run.argv]], env


def session_pids(sid: int) -> list[int]:
    out = []
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            stat = Path(f"/proc/{p}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        if len(fields) > 3 and int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(p))
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:120]
    except OSError:
        return "?"


def kill_session(sid: int):
    """SIGKILL every process of a session this harness started (by pid, one at a time)."""
    for pid in session_pids(sid):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def execute(run: Run, ctx: Ctx) -> list[RunResult]:
    argv, env = command(run)
    cwd = ctx.d / run.cwd
    procs = []
    t0 = time.perf_counter()
    for _ in range(run.copies):
        p = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             stdin=subprocess.DEVNULL, start_new_session=True)
        procs.append(p)
    results = []
    for p in procs:
        results.append(_watch(p, run, ctx, t0, argv))
    return results


def _watch(p, run: Run, ctx: Ctx, t0: float, argv) -> RunResult:
    lines = {"out": [], "err": []}
    fired = threading.Event()
    trig = run.signal[1] if run.signal else None

    def reader(stream, key):
        for raw in iter(stream.readline, b""):
            line = raw.decode(errors="replace")
            lines[key].append(line)
            if trig and trig[0] == "line" and re.search(trig[1], line):
                fired.set()
        stream.close()

    threads = [threading.Thread(target=reader, args=(p.stdout, "out"), daemon=True),
               threading.Thread(target=reader, args=(p.stderr, "err"), daemon=True)]
    for t in threads:
        t.start()
    res = RunResult(run.argv if run.argv is not None else ["<api>"], None, "", "", 0.0)
    deadline = t0 + run.timeout
    if run.signal:
        sig, _, to_group = run.signal
        while p.poll() is None and time.perf_counter() < deadline:
            if trig[0] == "time" and time.perf_counter() - t0 >= trig[1]:
                fired.set()
            if trig[0] == "file" and any(True for _ in _rglob(ctx.d, trig[1])):
                fired.set()
            if fired.is_set():
                break
            time.sleep(0.003)
        if fired.is_set() and len(trig) > 2:  # a delay after the trigger (e.g. to land inside a slowed call)
            end = time.perf_counter() + trig[2]
            while p.poll() is None and time.perf_counter() < end:
                time.sleep(0.01)
        if fired.is_set() and p.poll() is None:
            res.fired = True
            if run.probe:
                res.probe = run.probe(ctx, p)
            res.signalled = sig
            try:
                if to_group:
                    os.killpg(p.pid, sig)
                else:
                    os.kill(p.pid, sig)
            except OSError:
                pass
            deadline = time.perf_counter() + run.post_signal_timeout
    try:
        p.wait(timeout=max(0.1, deadline - time.perf_counter()))
    except subprocess.TimeoutExpired:
        res.timed_out = True
        try:
            os.kill(p.pid, signal.SIGKILL)
        except OSError:
            pass
        p.wait()
    res.seconds = time.perf_counter() - t0
    res.rc = p.returncode
    # processes of the session still alive after the main one ended (workers, trackers)
    end = time.perf_counter() + 4.0
    alive = session_pids(p.pid)
    while alive and time.perf_counter() < end:
        time.sleep(0.2)
        alive = session_pids(p.pid)
    if alive:
        res.survivors = [f"{pid}: {cmdline(pid)}" for pid in alive]
        kill_session(p.pid)
    for t in threads:
        t.join(timeout=5)
    res.out, res.err = "".join(lines["out"]), "".join(lines["err"])
    return res


def _rglob(d: Path, pattern: str):
    for root, dirs, files in os.walk(d):
        for n in files + dirs:
            if fnmatch.fnmatch(n, pattern):
                yield Path(root) / n


# ======================================================================================
# Classification
# ======================================================================================
PROGRESS = re.compile(r"^episeg: (?!error:)")        # progress, info and warning lines of the CLI
USAGE = re.compile(r"^(usage: |\s)")
ERROR_LINE = re.compile(r"^episeg(?: [\w-]+)?: error: (.*)$")
STACK_DUMP = re.compile(r"Traceback \(most recent call last\)|\*\*\* (SIG\w+|Aborted|Check failure)|^\s*@\s+0x"
                        r"|terminate called|Fatal Python error|core dumped", re.M)


def classify_run(run: Run, r: RunResult) -> list[tuple[str, str]]:
    found = []
    text = r.out + r.err
    sent = r.signalled
    if r.timed_out:
        found.append(("unbounded" if run.resource_case else "hang", f"no exit within {run.timeout:.0f} s"))
    elif r.rc is not None and r.rc < 0 and -r.rc != sent:
        found.append(("unbounded" if run.resource_case and -r.rc == signal.SIGKILL else "crash",
                      f"killed by signal {signal.Signals(-r.rc).name}"))
    if r.survivors:
        found.append(("leftover", f"{len(r.survivors)} process(es) alive after exit: " + "; ".join(r.survivors[:4])))
    if r.probe:
        found.append(("unbounded", r.probe))
    if STACK_DUMP.search(text):
        frames = len(re.findall(r"(?m)^\s*@\s+0x", text))
        last = ([ln for ln in text.splitlines() if re.match(r"^[\w.]+(Error|Exception|error|Interrupt)\b", ln)]
                or [ln for ln in text.strip().splitlines() if ln.strip()])[-1:] or ["?"]
        if frames and "Traceback" not in text:
            last = [f"a C++ stack dump of {frames} frames ({(re.findall(r'[*][*][*] .*', text) or [''])[0][:80]})"]
        if run.resource_case and re.search(r"MemoryError|bad_alloc|Unable to allocate|out of memory", text):
            found.append(("unbounded", f"out of memory under the cap: {last[0][:160]}"))
        else:
            found.append(("traceback", f"traceback/stack dump: {last[0][:200]}"))
    if found and any(o in ("hang", "crash", "unbounded") for o, _ in found) and not r.fired:
        return found
    if sent is not None and r.fired:
        return found + classify_signalled(run, r)
    if r.rc is None:
        return found
    if r.rc == 0:
        if run.expect == "error":
            found.append(("silent-wrong", "accepted (exit 0) where an error was expected"))
        elif run.check is not None:
            why = run.check(_CURRENT.ctx, r) if _CURRENT.ctx is not None else None
            if why:  # a check may name its class: "unbounded: ..."
                cls, _, rest = why.partition(": ")
                found.append((cls, rest) if cls in OUTCOMES else ("silent-wrong", why))
        if not found:
            found.append(("ok-result", ""))
        return found
    if any(o == "traceback" for o, _ in found):
        return found
    return found + classify_error(run, r)


def error_text(run: Run, r: RunResult) -> tuple[str | None, str]:
    """(the one error text, or None; a reason when it is not a clean single line)."""
    if run.code is not None:
        m = re.search(r"^API-ERROR (\w+) (\w+) (.*)$", r.err, re.M)
        if not m:
            return None, f"exit {r.rc} without an API error line"
        cat, typ, msg = m.group(1), m.group(2), json.loads(m.group(3))
        if cat not in run.cats:
            return None, f"{typ} is not a ValueError/TypeError: {msg[:160]!r}"
        if "\n" in msg.strip():
            return None, f"{typ} message has {len(msg.strip().splitlines())} lines: {msg[:160]!r}"
        return f"{typ}: {msg}", ""
    lines = [ln for ln in r.err.splitlines() if ln.strip()]
    errs = [m.group(1) for ln in lines if (m := ERROR_LINE.match(ln))]
    other = [ln for ln in lines if not ERROR_LINE.match(ln) and not PROGRESS.match(ln) and not USAGE.match(ln)]
    if r.rc not in (1, 2):
        return None, f"exit code {r.rc}"
    if len(errs) != 1:
        return None, f"{len(errs)} error lines on stderr: {r.err.strip()[-200:]!r}"
    if other:
        return None, f"extra output besides the error line: {other[0][:160]!r}"
    return errs[0], ""


MEMORY = re.compile(r"bad_alloc|MemoryError|Unable to allocate|Insufficient memory|out of memory|Cannot allocate", re.I)


def classify_error(run: Run, r: RunResult) -> list[tuple[str, str]]:
    msg, why = error_text(run, r)
    if run.resource_case and MEMORY.search(r.err):
        return [("unbounded", f"ran out of memory under the {run.mem_gb} GB cap: "
                              + (msg or why or r.err.strip().splitlines()[-1])[:200])]
    if msg is None:
        if run.code is not None and "is not a ValueError" in why:
            return [("traceback", why)]
        return [("bad-message", why)]
    missing = [rx for rx in run.err if not re.search(rx, msg, re.I)]
    if run.expect == "result":
        return [("refused", f"refused: {msg[:200]}")]
    if missing:
        return [("bad-message", f"message does not match {missing}: {msg[:200]}")]
    return [("ok-error", msg[:200])]


def classify_signalled(run: Run, r: RunResult) -> list[tuple[str, str]]:
    """After SIGINT/SIGTERM: a prompt end, a one-line notice, no stack dump. SIGKILL: nothing to check here."""
    sig = r.signalled
    if sig == signal.SIGKILL or r.timed_out:
        return [] if r.timed_out else [("ok-result", "")]
    lines = [ln for ln in r.err.splitlines() if ln.strip() and not PROGRESS.match(ln)]
    notice = [ln for ln in r.err.splitlines() if re.match(r"^episeg(: | \w+: )", ln)]
    if r.rc == -sig:
        return [("bad-message", f"ended by {signal.Signals(sig).name} itself: no notice, no clean-up")]
    if len(lines) > 1:
        return [("bad-message", f"{len(lines)} lines on stderr after {signal.Signals(sig).name}: "
                                f"{lines[0][:120]!r} ...")]
    if not notice or not re.search(r"interrupt|terminat|signal|stopp|cancel", r.err.splitlines()[-1] if r.err else "",
                                   re.I):
        return [("bad-message", f"no one-line notice after {signal.Signals(sig).name} (exit {r.rc}); "
                                f"last line {(r.err.strip().splitlines() or [''])[-1][:120]!r}")]
    return [("ok-result", "")]


class _Current(threading.local):
    ctx = None


_CURRENT = _Current()


# ======================================================================================
# Hashing inputs, leftovers
# ======================================================================================
def snapshot(d: Path, extra=()) -> dict:
    out = {}
    for root, _, files in os.walk(d):
        for n in files:
            p = Path(root) / n
            if p.is_symlink() or not p.is_file():
                continue
            out[str(p.relative_to(d))] = _sha(p)
    for e in extra:
        e = Path(e)
        for p in ([e] if e.is_file() else sorted(e.rglob("*")) if e.is_dir() else []):
            if p.is_file() and not p.is_symlink():
                out[str(p)] = _sha(p)
    return out


def _sha(p: Path) -> str:
    h = hashlib.sha1()
    try:
        with open(p, "rb") as f:
            for b in iter(lambda: f.read(1 << 20), b""):
                h.update(b)
    except OSError as e:
        return f"unreadable: {e}"
    return h.hexdigest()


def data_loss(before: dict, after: dict, mutable) -> list[str]:
    bad = []
    for k, h in before.items():
        if any(fnmatch.fnmatch(k, g) for g in mutable):
            continue
        if k not in after:
            bad.append(f"{k} deleted")
        elif after[k] != h:
            bad.append(f"{k} changed")
    return bad


def leftovers(d: Path, extra=()) -> list[str]:
    found = []
    for g in LEFTOVER_GLOBS:
        found += [str(p.relative_to(d)) for p in _rglob(d, g)]
    for g in extra:
        found += [str(p.relative_to(d)) for p in d.glob(g)]
    return sorted(set(found))


# ======================================================================================
# One case
# ======================================================================================
def run_case(case: Case, fix: Path, root: Path, keep: bool) -> dict:
    d = Path(tempfile.mkdtemp(prefix=re.sub(r"[^\w.-]", "_", case.name)[:60] + ".", dir=root))
    ctx = Ctx(d, fix)
    _CURRENT.ctx = ctx
    t0 = time.perf_counter()
    findings = []
    try:
        if case.setup:
            case.setup(d, fix)
        before = snapshot(d, case.extra_inputs)
        for run in case.runs:
            if run.action is not None:
                run.action(d, fix)
                continue
            for r in execute(run, ctx):
                ctx.results.append(r)
                findings += classify_run(run, r)
        after = snapshot(d, case.extra_inputs)
        lost = data_loss(before, after, case.mutable)
        if lost:
            findings.append(("data-loss", "; ".join(lost[:6])))
        left = leftovers(d, case.leftovers)
        if left:
            findings.append(("leftover", "left behind: " + ", ".join(left[:8])))
        if case.post:
            findings += case.post(ctx) or []
    except Exception as e:  # a harness error must not hide the others
        import traceback

        findings.append(("crash", f"HARNESS ERROR {type(e).__name__}: {e}\n{traceback.format_exc()[-800:]}"))
    finally:
        _CURRENT.ctx = None
    order = {o: i for i, o in enumerate(SEVERITY)}
    findings = findings or [("ok-result", "")]
    worst = min(findings, key=lambda f: order.get(f[0], 0))[0]
    reasons = [f"{o}: {w}" for o, w in findings if o != "ok-result" and w]
    rec = {"name": case.name, "group": case.group, "doc": case.doc, "outcome": worst, "reasons": reasons,
           "seconds": round(time.perf_counter() - t0, 2), "folder": str(d),
           "repro": repro(case, d),
           "runs": [{"argv": r.argv, "rc": r.rc, "seconds": round(r.seconds, 2), "signalled": r.signalled,
                     "stderr_tail": r.err[-4000:], "stdout_tail": r.out[-600:]} for r in ctx.results]}
    if worst in ("ok-result", "ok-error") and not keep:
        shutil.rmtree(d, ignore_errors=True)
        rec["folder"] = None
    return rec


def repro(case: Case, d: Path) -> str:
    parts = []
    for run in case.runs:
        env = f"PYTHONPATH={os.environ.get('PYTHONPATH', '')} "
        if run.action is not None:
            parts.append(f"({(run.action.__doc__ or run.action.__name__).strip()})")
        elif run.code is not None:
            parts.append(f"(API) {textwrap.dedent(run.code).strip()}")
        else:
            extra = []
            if run.mem_gb:
                extra.append(f"RLIMIT_AS={run.mem_gb} GB")
            if run.slow:
                extra.append(f"slowed: {run.slow}")
            if run.signal:
                extra.append(f"{signal.Signals(run.signal[0]).name} {'to the group ' if run.signal[2] else ''}"
                             f"on {run.signal[1]}")
            if run.copies > 1:
                extra.append(f"{run.copies} copies at once")
            parts.append(env + f"python -m {PATHS['cli']} " + shlex.join(str(a) for a in run.argv)
                         + (f"   [{'; '.join(extra)}]" if extra else ""))
    return " && ".join(parts)


# ======================================================================================
# Fixtures (built once per harness run)
# ======================================================================================
FIXTURE_CODE = r'''
import sys, json, importlib
from pathlib import Path
import numpy as np, cv2
P = json.loads(sys.argv[2])
fix = Path(sys.argv[1])
def _imp(spec):
    mod, _, attr = spec.partition(":")
    m = importlib.import_module(mod)
    for a in filter(None, attr.split(".")):
        m = getattr(m, a)
    return m
ep = _imp(P["pkg"]); scenes = _imp(P["scenes"])
d = fix / "pair"; d.mkdir(parents=True, exist_ok=True)
pair = scenes.make_pair("forward", image_size=(320, 240))
cv2.imwrite(str(d / "img1.png"), pair.image1); cv2.imwrite(str(d / "img2.png"), pair.image2)
cv2.imwrite(str(d / "tiny.png"), np.full((1, 1), 128, np.uint8))
cv2.imwrite(str(d / "small.png"), pair.image1[:120, :160])
g = pair.geometry
calib = {"K1": g.K1.tolist(), "K2": g.K2.tolist(), "R": g.R.tolist(), "t": g.t.tolist(),
         "image_size1": list(g.image_size1), "image_size2": list(g.image_size2)}
(d / "calib.json").write_text(json.dumps(calib, indent=1))
ep.save_calibration(d / "calib.yml", g)
ep.save_calibration(d / "calib.xml", g)
import pycolmap
for c in ("coll", "big"):
    m = fix / c / "model"
    if m.is_dir():
        t = fix / c / "model_txt"; t.mkdir(exist_ok=True)
        pycolmap.Reconstruction(str(m)).write_text(str(t))
'''


def build_fixtures(fix: Path, log=print):
    stamp = fix / "STAMP"
    want = json.dumps({"paths": PATHS, "pythonpath": os.environ.get("PYTHONPATH", ""), "v": 3})
    if stamp.is_file() and stamp.read_text() == want:
        return
    if fix.exists():
        shutil.rmtree(fix)
    fix.mkdir(parents=True)
    env = base_env()
    cli = [PY, "-m", PATHS["cli"]]

    def sh(argv, cwd=fix):
        r = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
        if r.returncode != 0:
            raise RuntimeError(f"fixture step failed: {shlex.join(argv)}\n{r.stdout}\n{r.stderr}")
        return r

    t0 = time.perf_counter()
    log("building fixtures in", fix)
    sh(cli + ["synthetic", "coll", "--views", "4", "--size", "160", "120", "-q"])
    sh(cli + ["synthetic", "big", "--views", "8", "--size", "640", "480", "-q"])
    sh([PY, "-c", FIXTURE_CODE, str(fix), json.dumps(PATHS)])
    # a complete database (default settings), and half-done ones (3 of 6 pairs) for --resume
    c = fix / "coll"
    (c / "pairs_half.txt").write_text("view_000.png view_001.png\nview_001.png view_002.png\n"
                                      "view_002.png view_003.png\n")
    (c / "pairs_all.txt").write_text("".join(f"view_{i:03d}.png view_{j:03d}.png\n"
                                             for i in range(4) for j in range(i + 1, 4)))
    sh(cli + ["colmap", "model", "images", "--database", "done.db", "-q"], cwd=c)
    sh(cli + ["colmap", "model", "images", "--database", "half.db", "--pairs", "pairs_half.txt", "-q"], cwd=c)
    sh(cli + ["colmap", "model", "images", "--database", "half100.db", "--pairs", "pairs_half.txt",
              "--max-features", "100", "-q"], cwd=c)
    # matches files
    p = fix / "pair"
    for ext in ("json", "npz", "csv"):
        sh(cli + ["match", "img1.png", "img2.png", "--calib", "calib.json", "--out", f"m.{ext}", "-q"], cwd=p)
    # the big collection's feature cache (signal tests during the pair phase start there)
    sh(cli + ["colmap", "model", "images", "--database", "full.db", "--cache", "cache", "-q"], cwd=fix / "big")
    # dinoSparseRing as a poses JSON (world-to-camera, as in dinoSR_par.txt)
    build_dino(fix / "dino")
    stamp.write_text(want)
    log(f"fixtures ready in {time.perf_counter() - t0:.0f} s")


def dino_views():
    par = DINO / "dinoSR_par.txt"
    if not par.is_file():
        return []
    out = []
    for line in par.read_text().splitlines()[1:]:
        v = line.split()
        if len(v) != 22:
            continue
        nums = [float(x) for x in v[1:]]
        K = [nums[0:3], nums[3:6], nums[6:9]]
        R = [nums[9:12], nums[12:15], nums[15:18]]
        out.append({"name": v[0], "K": K, "R": R, "t": nums[18:21], "width": 640, "height": 480})
    return out


def build_dino(d: Path):
    d.mkdir(parents=True, exist_ok=True)
    views = dino_views()
    if not views:
        return
    (d / "poses.json").write_text(json.dumps({"images": views}, indent=1))
    (d / "pairs.txt").write_text(f"{views[0]['name']} {views[1]['name']}\n")
    a, b = views[0], views[1]
    (d / "calib_world.json").write_text(json.dumps(
        {"K1": a["K"], "R1": a["R"], "t1": a["t"], "K2": b["K"], "R2": b["R"], "t2": b["t"],
         "image_size1": [640, 480], "image_size2": [640, 480]}, indent=1))
    (d / "calib_cameras.json").write_text(json.dumps(
        {"cameras": [{"K": a["K"], "R": a["R"], "t": a["t"], "image_size": [640, 480]},
                     {"K": b["K"], "R": b["R"], "t": b["t"], "image_size": [640, 480]}]}, indent=1))


# ======================================================================================
# Setup helpers
# ======================================================================================
def S(*steps):
    """Compose setup steps."""
    def setup(d, fix):
        for s in steps:
            s(d, fix)
    return setup


def cp(src: str, dst: str | None = None):
    """Copy fixture path ``src`` (relative to the fixtures) to ``dst`` (relative to the case folder)."""
    def step(d, fix):
        s, t = fix / src, d / (dst if dst is not None else Path(src).name)
        if s.is_dir():
            shutil.copytree(s, t, dirs_exist_ok=True)
        else:
            t.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(s, t)
    return step


PAIR = S(cp("pair/img1.png"), cp("pair/img2.png"), cp("pair/calib.json"))
COLL = S(cp("coll/images", "images"), cp("coll/model", "model"), cp("coll/poses.json", "poses.json"))
BIG = S(cp("big/images", "images"), cp("big/model", "model"))
BIG_CACHED = S(BIG, cp("big/cache", "db.db.features"))


def write(name: str, content):
    """Write a file: str, bytes, or a callable (d, fix) -> str | bytes."""
    def step(d, fix):
        c = content(d, fix) if callable(content) else content
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(c, bytes):
            p.write_bytes(c)
        else:
            p.write_text(c)
    return step


def mkdir(name: str):
    return lambda d, fix: (d / name).mkdir(parents=True, exist_ok=True)


def symlink(name: str, target: str):
    return lambda d, fix: os.symlink(target, d / name)


def truncate(name: str, keep):
    """Keep the first ``keep`` bytes (int) or fraction (float) of a case file."""
    def step(d, fix):
        p = d / name
        b = p.read_bytes()
        n = keep if isinstance(keep, int) else int(len(b) * keep)
        p.write_bytes(b[:n])
    return step


def edit(name: str, fn):
    """Rewrite a text case file with ``fn(text) -> text``."""
    def step(d, fix):
        p = d / name
        p.write_text(fn(p.read_text()))
    return step


def phone_jpegs(orientation: int = 6):
    """The collection's images as JPEGs tagged with an EXIF orientation (a phone's portrait pictures), and the
    poses JSON renamed to them: COLMAP reads them in their stored grid, as their poses are."""
    def step(d, fix):
        from PIL import Image

        for png in sorted((d / "images").glob("*.png")):
            exif = Image.Exif()
            exif[0x0112] = orientation
            with Image.open(png) as im:
                im.convert("L").save(png.with_suffix(".jpg"), quality=95, exif=exif.tobytes())
            png.unlink()
        poses = d / "poses.json"
        poses.write_text(poses.read_text().replace(".png", ".jpg"))
    return step


def base_calib(fix) -> dict:
    return json.loads((fix / "pair" / "calib.json").read_text())


def calib_variant(mutate, name="c.json", raw=False):
    """A JSON calibration derived from the fixture's: ``mutate(dict) -> dict`` (or text when raw)."""
    def content(d, fix):
        c = mutate(base_calib(fix))
        return c if raw else json.dumps(c)
    return write(name, content)


def poses_variant(mutate, name="p.json", raw=False):
    def content(d, fix):
        c = mutate(json.loads((fix / "coll" / "poses.json").read_text()))
        return c if raw else json.dumps(c)
    return write(name, content)


def set_in(path, value):
    """``mutate`` that sets ``obj[path[0]][path[1]]... = value`` (a callable value gets the old one)."""
    def mutate(obj):
        o = obj
        for k in path[:-1]:
            o = o[k]
        o[path[-1]] = value(o[path[-1]]) if callable(value) else value
        return obj
    return mutate


def drop(*keys):
    def mutate(obj):
        for k in keys:
            obj.pop(k, None)
        return obj
    return mutate


def drop_in_image(i, *keys):
    def mutate(obj):
        for k in keys:
            obj["images"][i].pop(k, None)
        return obj
    return mutate


def nested(depth: int, leaf="1") -> str:
    return "[" * depth + leaf + "]" * depth


def mat(rows, cols, data, dt="d"):
    return ("mat", rows, cols, list(data), dt)


def cv_yaml(entries: dict) -> str:
    out = ["%YAML:1.0", "---"]
    for k, v in entries.items():
        if isinstance(v, tuple) and v and v[0] == "mat":
            _, r, c, data, dt = v
            out += [f"{k}: !!opencv-matrix", f"   rows: {r}", f"   cols: {c}", f"   dt: {dt}",
                    "   data: [ " + ", ".join(_num(x) for x in data) + " ]"]
        else:
            out.append(f"{k}: {v}")
    return "\n".join(out) + "\n"


def cv_xml(entries: dict) -> str:
    out = ['<?xml version="1.0"?>', "<opencv_storage>"]
    for k, v in entries.items():
        if isinstance(v, tuple) and v and v[0] == "mat":
            _, r, c, data, dt = v
            out.append(f'<{k} type_id="opencv-matrix"><rows>{r}</rows><cols>{c}</cols><dt>{dt}</dt>'
                       f"<data>{' '.join(_num(x) for x in data)}</data></{k}>")
        else:
            out.append(f"<{k}>{v}</{k}>")
    return "\n".join(out + ["</opencv_storage>"]) + "\n"


def _num(x) -> str:
    if isinstance(x, str):
        return x
    if x != x:
        return ".nan"
    if x in (float("inf"), float("-inf")):
        return ".inf" if x > 0 else "-.inf"
    return repr(float(x))


def cv_entries(fix, **changes) -> dict:
    """OpenCV stereoCalibrate names from the fixture calibration; ``changes`` replace or (None) drop keys."""
    c = base_calib(fix)
    flat = lambda m: [x for row in m for x in row]  # noqa: E731
    e = {"M1": mat(3, 3, flat(c["K1"])), "D1": mat(1, 5, [0] * 5), "M2": mat(3, 3, flat(c["K2"])),
         "D2": mat(1, 5, [0] * 5), "R": mat(3, 3, flat(c["R"])), "T": mat(3, 1, c["t"]),
         "image_width": 320, "image_height": 240}
    for k, v in changes.items():
        if v is None:
            e.pop(k, None)
        else:
            e[k] = v(e.get(k)) if callable(v) else v
    return e


def yaml_variant(name="c.yml", xml=False, **changes):
    return write(name, lambda d, fix: (cv_xml if xml else cv_yaml)(cv_entries(fix, **changes)))


# ======================================================================================
# Checks
# ======================================================================================
def db_check(path: Path, expect_images: int | None = None) -> str | None:
    """A usable COLMAP database: integrity, whole pairs (matches <=> geometry), indices in range."""
    if not path.is_file():
        return f"{path.name} missing"
    with tempfile.TemporaryDirectory() as tmp:  # a copy: a reader must not leave -shm/-wal in the case folder
        copy = Path(tmp) / path.name
        for suffix in ("", "-wal"):
            if Path(str(path) + suffix).is_file():
                shutil.copy2(str(path) + suffix, str(copy) + suffix)
        return _db_check(copy, path.name, expect_images)


def _db_check(path: Path, label: str, expect_images) -> str | None:
    try:
        con = sqlite3.connect(str(path), timeout=5)
        try:
            if con.execute("PRAGMA integrity_check").fetchone()[0] != "ok":
                return f"{label}: sqlite integrity check failed"
            n_img = con.execute("SELECT count(*) FROM images").fetchone()[0]
            if expect_images is not None and n_img != expect_images:
                return f"{label}: {n_img} images, expected {expect_images}"
            kp = {i: r for i, r in con.execute("SELECT image_id, rows FROM keypoints")}
            m = {pid: (r, data) for pid, r, data in con.execute("SELECT pair_id, rows, data FROM matches")}
            g = {pid for (pid,) in con.execute("SELECT pair_id FROM two_view_geometries")}
        finally:
            con.close()
    except sqlite3.Error as e:
        return f"{label}: not a usable database ({e})"
    half = [pid for pid, (r, _) in m.items() if r and pid not in g]
    if half:
        return f"{label}: {len(half)} pair(s) with matches but no two-view geometry (half-written)"
    import array

    for pid, (r, data) in m.items():
        if not r or data is None:
            continue
        a, b = divmod(pid, 2147483647)
        idx = array.array("I", data)
        if max(idx[0::2]) >= kp.get(a, 0) or max(idx[1::2]) >= kp.get(b, 0):
            return f"{label}: pair {a}-{b} has keypoint indices beyond the stored keypoints"
    return None


def check_db(name="db.db", images=None, pairs_at_least=None):
    def check(ctx, r):
        why = db_check(ctx.d / name, images)
        if why:
            return why
        if pairs_at_least is not None:
            with tempfile.TemporaryDirectory() as tmp:
                shutil.copy2(ctx.d / name, Path(tmp) / name)
                if (ctx.d / (name + "-wal")).is_file():
                    shutil.copy2(ctx.d / (name + "-wal"), Path(tmp) / (name + "-wal"))
                con = sqlite3.connect(str(Path(tmp) / name))
                n = con.execute("SELECT count(*) FROM two_view_geometries").fetchone()[0]
                con.close()
            if n < pairs_at_least:
                return f"{name}: {n} pairs, expected at least {pairs_at_least}"
        return None
    return check


def post_db(name="db.db", images=None, optional=True):
    """After a signal: the database, if it exists, is usable with whole pairs only."""
    def post(ctx):
        p = ctx.d / name
        if optional and not p.exists():
            return []
        why = db_check(p, images)
        return [("data-loss", why)] if why else []
    return post


def _keypoints(db: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "k.db"
        shutil.copy2(db, copy)
        if Path(str(db) + "-wal").is_file():
            shutil.copy2(str(db) + "-wal", str(copy) + "-wal")
        con = sqlite3.connect(str(copy))
        names = dict(con.execute("SELECT image_id, name FROM images"))
        out = {names.get(i, i): bytes(data or b"") for i, data in con.execute("SELECT image_id, data FROM keypoints")}
        con.close()
    return out


def check_keypoints_fresh(name="db.db", extra=()):
    """Every image's keypoints in the database are those a fresh run (no cache, same options) finds in the
    images now on disk: the CLI is run again in a clean folder outside the case."""
    def check(ctx, r):
        with tempfile.TemporaryDirectory() as tmp:
            for sub in ("images", "model"):
                shutil.copytree(ctx.d / sub, Path(tmp) / sub)
            p = subprocess.run([PY, "-m", PATHS["cli"], "colmap", "model", "images", "--database", "fresh.db", "-q",
                                *extra], cwd=tmp, env=base_env(), capture_output=True, text=True, timeout=300)
            if p.returncode != 0:
                return f"the fresh run for the keypoint check failed: {p.stderr.strip()[-200:]}"
            fresh = _keypoints(Path(tmp) / "fresh.db")
        have = _keypoints(ctx.d / name)
        bad = sorted(n for n in fresh if have.get(n) != fresh[n])
        return (f"database keypoints of {bad} are not those of the image now on disk (stale features used)"
                if bad else None)
    return check


def check_files(*names, nonempty=True):
    def check(ctx, r):
        for n in names:
            p = ctx.d / n
            if not p.exists() or (nonempty and p.is_file() and p.stat().st_size == 0):
                return f"{n} not written"
        return None
    return check


def check_api(fn):
    """Check on the API's JSON summary: ``fn(value) -> None or reason``."""
    def check(ctx, r):
        m = re.search(r"^API-RESULT (.*)$", r.out, re.M)
        if not m:
            return "no API-RESULT line"
        return fn(json.loads(m.group(1)))
    return check


def check_stdout(rx, absent=False):
    def check(ctx, r):
        hit = re.search(rx, r.out, re.M)
        if absent and hit:
            return f"stdout has {rx!r}"
        if not absent and not hit:
            return f"stdout lacks {rx!r}: {r.out[-200:]!r}"
        return None
    return check


def check_no_warning(ctx, r):
    if re.search(r"Warning|overflow", r.err):
        return "only a warning on stderr: " + [ln for ln in r.err.splitlines() if "arning" in ln][0][:160]
    return None


def all_of(*checks):
    def check(ctx, r):
        for c in checks:
            if c is not None:
                why = c(ctx, r)
                if why:
                    return why
        return None
    return check


# ======================================================================================
# The cases
# ======================================================================================
def cases() -> list[Case]:
    return build()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=None, metavar="REGEX", help="run the cases whose name or group matches")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    ap.add_argument("--json", type=Path, default=None, help="write per-case outcomes here")
    ap.add_argument("--workdir", type=Path, default=None, help="case folders and fixtures (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the folders of passing cases too")
    ap.add_argument("--md", type=Path, default=None, help="write the summary table here, as markdown")
    args = ap.parse_args(argv)
    # Started in the background (nohup, '&' without job control), SIGINT is ignored and children inherit
    # that: Python then never raises KeyboardInterrupt, and the Ctrl-C cases would test nothing.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)

    all_cases = cases()
    names = [c.name for c in all_cases]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise SystemExit(f"duplicate case names: {sorted(dup)}")
    sel = [c for c in all_cases if args.only is None or re.search(args.only, c.name) or re.search(args.only, c.group)]
    if args.list:
        for c in sel:
            print(f"{c.group:16s} {c.name:50s} {c.doc}")
        print(f"{len(sel)} cases")
        return 0
    root = (args.workdir or Path(tempfile.mkdtemp(prefix="episeg_faults."))).resolve()
    root.mkdir(parents=True, exist_ok=True)
    fix = root / "fixtures"
    build_fixtures(fix)
    cases_dir = root / "cases"
    cases_dir.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    results = []
    lock = threading.Lock()

    def one(c):
        rec = run_case(c, fix, cases_dir, args.keep)
        with lock:
            results.append(rec)
            mark = "  " if rec["outcome"] in ("ok-result", "ok-error") else "!!"
            print(f"{mark} [{len(results):3d}/{len(sel)}] {rec['outcome']:12s} {c.name} ({rec['seconds']:.1f} s)"
                  + (f"\n      {rec['reasons'][0][:220]}" if rec["reasons"] and mark == "!!" else ""), flush=True)
        return rec

    shared = [c for c in sel if not c.exclusive]
    alone = [c for c in sel if c.exclusive]
    with cf.ThreadPoolExecutor(max(1, args.jobs)) as ex:
        list(ex.map(one, shared))
    for c in alone:
        one(c)
    results.sort(key=lambda r: names.index(r["name"]))
    print()
    print(summary_table(results))
    print(f"\n{len(results)} cases in {time.perf_counter() - t0:.0f} s; "
          f"{sum(r['outcome'] in BAD for r in results)} fail; folders of failing cases under {cases_dir}")
    out = args.json or (root / "faults.json")
    out.write_text(json.dumps({"pythonpath": os.environ.get("PYTHONPATH", ""), "paths": PATHS,
                               "counts": {o: sum(r["outcome"] == o for r in results) for o in OUTCOMES},
                               "cases": results}, indent=1))
    print(f"per-case outcomes: {out}")
    if args.md:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True)
        bad = [r for r in results if r["outcome"] in BAD]
        args.md.write_text(
            "# Bad input and faults, tried as a user would\n\n"
            f"Made by `python benchmarks/faults.py {' '.join(argv if argv is not None else sys.argv[1:])}` on "
            f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')} in {time.perf_counter() - t0:.0f} s (git HEAD "
            f"{head.stdout.strip() or 'unknown'}, python {platform.python_version()}, {os.cpu_count()} cores). "
            "Each case runs as a subprocess in a fresh folder; the outcomes are defined in the script's docstring "
            "(`ok-error`: exactly one error line that names the argument or file and what was expected; "
            "`ok-result`: exit 0 and the case's checks pass; anything else fails).\n\n"
            "```\n" + summary_table(results) + "\n```\n\n"
            f"{len(results)} cases, {len(bad)} failing"
            + (": " + ", ".join(f"`{r['name']}` ({r['outcome']})" for r in bad) if bad else "") + ".\n")
        print(f"summary: {args.md}")
    return 1 if any(r["outcome"] in BAD for r in results) else 0


def summary_table(results) -> str:
    groups = sorted({r["group"] for r in results}, key=lambda g: [r["group"] for r in results].index(g))
    cols = [o for o in OUTCOMES if any(r["outcome"] == o for r in results)]
    rows = [["group", *cols, "total"]]
    for g in groups:
        rs = [r for r in results if r["group"] == g]
        rows.append([g, *[str(sum(r["outcome"] == o for r in rs) or "") for o in cols], str(len(rs))])
    rows.append(["total", *[str(sum(r["outcome"] == o for r in results)) for o in cols], str(len(results))])
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    fmt = lambda r: "  ".join(c.ljust(w[i]) if i == 0 else c.rjust(w[i]) for i, c in enumerate(r))  # noqa: E731
    return "\n".join([fmt(rows[0]), "  ".join("-" * x for x in w), *map(fmt, rows[1:])])


# ======================================================================================
# The catalogue
# ======================================================================================
MATCH = ["match", "img1.png", "img2.png", "--calib", "calib.json"]
SEG_C = ["segments", "img1.png", "img2.png", "--calib", "c.json", "--points", "160,120", "--out", "fig.png"]
COLMAP = ["colmap", "model", "images", "--database", "db.db"]
COLMAP_P = ["colmap", "p.json", "images", "--database", "db.db"]
DB_MUT = ("db.db", "db.db.features/*", "db.db.features")
DR = r"-?-?depth.range"   # the option or its API name
NOT_FE = r"^(?!.*File exists)"  # errno text that says nothing about what was expected
FIG = check_files("fig.png")


def C(name, group, doc, argv, setup=None, expect="error", err=(), check=None, **kw) -> Case:
    """A CLI case with one run."""
    ck = {k: kw.pop(k) for k in ("mutable", "extra_inputs", "leftovers", "post", "exclusive") if k in kw}
    return Case(name, group, doc, [Run(argv=list(argv), expect=expect, err=tuple(err), check=check, **kw)],
                setup=setup, **ck)


def A(name, group, doc, code, expect="error", err=(), check=None, setup=None, **kw) -> Case:
    """An API case: ``code`` is a function body (or one expression) run after the prelude."""
    ck = {k: kw.pop(k) for k in ("mutable", "extra_inputs", "leftovers", "post", "exclusive") if k in kw}
    return Case(name, group, doc, [Run(code=code, expect=expect, err=tuple(err), check=check, **kw)],
                setup=setup, **ck)


def _rot5(R):
    return [[round(x, 5) for x in row] for row in R]


def _round_trip_check(ctx, r):
    """k1 = -5: every undistorted keypoint must map back (re-distort) to its detected position."""
    code = r'''
import json, sys, numpy as np, cv2
m = json.load(open("m.json")); c = json.load(open("c.json"))
K = np.array(c["K1"]); d = np.array(c["dist1"], float)
k = np.array(m["keypoints1"]); u = np.array(m.get("keypoints1_undistorted", m["keypoints1"]), dtype=float)
lab = np.array(m["labels"]); idx = np.array(m["matches"]).reshape(-1, 2)[:, 0]
n = (u - K[:2, 2]) / [K[0, 0], K[1, 1]]
back = cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
bad = ~(np.linalg.norm(back - k, axis=1) <= 1.0)  # NaN (no inverse) counts as bad if matched
on = lab == "on_segment"
print(json.dumps({"bad_keypoints": int(bad.sum()), "n": len(k), "bad_on_segment": int(bad[idx][on].sum()) if len(idx) else 0,
                  "on_segment": int(on.sum())}))
'''
    p = subprocess.run([PY, "-c", code], cwd=ctx.d, env=base_env(), capture_output=True, text=True, timeout=60)
    if p.returncode != 0:
        return f"round-trip check failed: {p.stderr.strip()[-200:]}"
    v = json.loads(p.stdout)
    if v["bad_on_segment"]:
        return (f"{v['bad_on_segment']} of {v['on_segment']} on-segment matches use keypoints whose undistorted "
                f"position does not map back ({v['bad_keypoints']} of {v['n']} keypoints)")
    return None


def g_cli_flags() -> list[Case]:
    G = "cli-flags"
    out = []
    for flag, val, err in [("--tol", "-1", (r"--tol", ">= 0")), ("--tol", "nan", (r"--tol", "finite")),
                           ("--tol", "inf", (r"--tol", "finite")), ("--tol", "abc", (r"--tol", "number")),
                           ("--ratio", "0", (r"--ratio", r"\(0, 1\]")), ("--ratio", "1.5", (r"--ratio", r"\(0, 1\]")),
                           ("--ratio", "-0.1", (r"--ratio",)), ("--ratio", "nan", (r"--ratio",)),
                           ("--max-features", "0", (r"--max-features", r"positive|integer in \[1,")),
                           ("--max-features", "-5", (r"--max-features", r"positive|integer in \[1,")),
                           ("--max-features", "1e3", (r"--max-features", "integer")),
                           ("--constraint", "bogus", (r"--constraint", "choice")),
                           ("--detector", "bogus", (r"--detector", "choice"))]:
        out.append(C(f"match {flag} {val}", G, f"episeg match with {flag} {val}", MATCH + [flag, val], PAIR, err=err))
    out.append(C("match --max-features 10^30", G, "a keypoint cap beyond any integer type (issue)",
                 MATCH + ["--max-features", "1" + "0" * 30], PAIR, expect="either", err=("--max-features",)))
    for a, b, err in [("5", "1", (DR, "zmin < zmax|ZMIN.*ZMAX")), ("-1", "5", (DR, ">= 0")),
                      ("nan", "5", (DR,)), ("0", "0", (DR, "zmin < zmax|ZMIN.*ZMAX")),
                      ("inf", "inf", (DR,))]:
        out.append(C(f"match --depth-range {a} {b}", G, "bad depth range", MATCH + ["--depth-range", a, b], PAIR, err=err))
    out += [
        C("match --depth-range one value", G, "nargs 2 given 1", MATCH + ["--depth-range", "1"], PAIR,
          err=(DR, "2|two")),
        C("match --detector orb", G, "ORB works", MATCH + ["--detector", "orb", "--out", "m.json"], PAIR,
          expect="result", check=check_files("m.json")),
        C("match --detector akaze", G, "AKAZE works", MATCH + ["--detector", "akaze", "--out", "m.npz"], PAIR,
          expect="result", check=check_files("m.npz")),
        C("match --constraint none --cross-check", G, "plain BFMatcher crossCheck",
          MATCH + ["--constraint", "none", "--cross-check", "--out", "m.csv"], PAIR, expect="result",
          check=check_files("m.csv")),
        C("match --tol 1e308", G, "a huge but finite tolerance", MATCH + ["--tol", "1e308"], PAIR, expect="either",
          err=("--tol",)),
        C("match without --calib", G, "no pose: F estimated, matched on its half-lines (issue 16)",
          ["match", "img1.png", "img2.png", "--out", "m.json"], PAIR, expect="result", check=check_files("m.json")),
        C("unknown option", G, "--foo", MATCH + ["--foo"], PAIR, err=("--foo", "unrecognized")),
        C("no subcommand", G, "bare episeg", [], None, err=("command|COMMAND", "required")),
        C("--version", G, "version", ["--version"], None, expect="result", check=check_stdout(r"\d+\.\d+")),
    ]
    SEG = ["segments", "img1.png", "img2.png", "--calib", "calib.json", "--out", "fig.png"]
    for extra, err in [(["--random", "0"], ("--random", r"positive|integer in \[1,")), (["--random", "-3"], ("--random", r"positive|integer in \[1,")),
                       (["--points", "1,2,3"], ("--points|point", "x,y")), (["--points", "nan,5"], ("point", "finite")),
                       (["--points", "1000,1000"], ("point", "outside")), (["--points", "abc"], ("point", "x,y")),
                       (["--random", "5", "--points", "1,1"], ("--points|--random", "not allowed|exclusive")),
                       (["--seed", "abc"], ("--seed", "int")), (["--points", "inf,3"], ("point", "finite"))]:
        out.append(C("segments " + " ".join(extra), G, "bad segments option", SEG + extra, PAIR, err=err))
    out.append(C("segments --random 3", G, "works", SEG + ["--random", "3"], PAIR, expect="result", check=FIG))
    SYN = ["synthetic", "syn"]
    for extra, err in [(["--views", "0"], ("--views", r"positive|integer in \[2,")), (["--views", "1"], ("--views", "2")),
                       (["--size", "0", "10"], ("--size", r"positive|integer in \[16,")), (["--size", "10"], ("--size", "2|W H|two")),
                       (["--views", "abc"], ("--views", "integer"))]:
        out.append(C("synthetic " + " ".join(extra), G, "bad synthetic option", SYN + extra, None, err=err,
                     leftovers=("syn",)))
    out.append(C("synthetic --size 8 6", G, "a tiny collection", SYN + ["--views", "2", "--size", "8", "6"], None,
                 expect="either", err=("--size",)))
    out.append(C("synthetic --seed -1", G, "negative seed", SYN + ["--views", "2", "--size", "64", "48", "--seed", "-1"],
                 None, expect="either", err=("--seed",)))
    for extra, err in [(["--workers", "0"], ("--workers", "positive")), (["--workers", "abc"], ("--workers", "integer")),
                       (["--neighbors", "0"], ("--neighbors", "positive")),
                       (["--neighbors", "2", "--pairs", "x.txt"], ("--pairs|--neighbors", "not allowed")),
                       (["--resume", "--overwrite"], ("--overwrite|--resume", "not allowed")),
                       (["--depth-range", "1"], (DR,)), (["--depth-range", "5", "1"], (DR, "zmin|<")),
                       (["--depth-range", "foo"], (DR,)), (["--depth-range", "1", "2", "3"], (DR,)),
                       (["--depth-range", "-1", "2"], (DR, ">= 0")),
                       (["--scheduler", "local:0"], ("scheduler", "positive")),
                       (["--scheduler", "local:abc"], ("scheduler", "positive|integer")),
                       (["--tol", "-1"], ("--tol",)), (["--ratio", "2"], ("--ratio",)),
                       (["--constraint", "none"], ("--constraint", "choice")),
                       (["--max-features", "1" + "0" * 30], ("--max-features",))]:
        exp = "either" if "--max-features" in extra else "error"
        out.append(C("colmap " + " ".join(e if len(e) < 12 or not e.isdigit() else "10^30" for e in extra), G,
                     "bad colmap option",
                     COLMAP + extra, COLL, expect=exp, err=err, mutable=DB_MUT, check=check_db()))
    out.append(C("colmap --scheduler unreachable", G, "a Dask scheduler that is not there",
                 COLMAP + ["--scheduler", "tcp://127.0.0.1:9"], COLL, err=("scheduler", "reach|connect"),
                 timeout=90))
    for extra in (["--depth-range", "none"], ["--depth-range", "0.1", "100"], ["--detector", "orb"], ["--neighbors", "1"]):
        out.append(C("colmap " + " ".join(extra), G, "valid colmap option", COLMAP + extra, COLL, expect="result",
                     check=check_db("db.db", 4)))
    out += [
        C("demo --max-features 0", G, "bad demo option", ["demo", "--max-features", "0", "--out", "o"], None,
          err=("--max-features",)),
        C("demo --points 0", G, "bad demo option", ["demo", "--points", "0", "--out", "o"], None, err=("--points",)),
    ]
    return out


def g_cli_files() -> list[Case]:
    G = "cli-files"
    garbage = bytes(range(256)) * 8
    png = lambda d, fix: (fix / "pair" / "img1.png").read_bytes()  # noqa: E731
    out = [
        C("image missing", G, "image 1 does not exist", ["match", "nope.png", "img2.png", "--calib", "calib.json"],
          PAIR, err=("nope.png", "not found|no such|does not exist")),
        C("image is a folder", G, "a folder given as image 1 (issue: says 'not found')",
          ["match", "imgdir", "img2.png", "--calib", "calib.json"], S(PAIR, mkdir("imgdir")),
          err=("imgdir", "folder|directory")),
        C("image 0-byte", G, "empty image file", MATCH[:1] + ["e.png", "img2.png", "--calib", "calib.json"],
          S(PAIR, write("e.png", b"")), err=("e.png", "read|decode|empty")),
        C("image is text", G, "a text file named .png", ["match", "t.png", "img2.png", "--calib", "calib.json"],
          S(PAIR, write("t.png", "hello\n")), err=("t.png", "read|decode")),
        C("image garbage bytes", G, "random bytes named .jpg", ["match", "g.jpg", "img2.png", "--calib", "calib.json"],
          S(PAIR, write("g.jpg", garbage)), err=("g.jpg", "read|decode")),
        C("image truncated PNG", G, "the first 300 bytes of a PNG",
          ["match", "tr.png", "img2.png", "--calib", "calib.json"], S(PAIR, write("tr.png", lambda d, f: png(d, f)[:300])),
          expect="either", err=("tr.png", "read|decode|truncat|corrupt")),
        C("image 1x1, calibration without sizes", G, "issue: a traceback",
          ["match", "tiny.png", "tiny.png", "--calib", "c.json"],
          S(PAIR, cp("pair/tiny.png"), calib_variant(drop("image_size1", "image_size2"))),
          expect="either", err=("tiny.png|image|size",)),
        C("image 1x1, calibration with sizes", G, "size mismatch",
          ["match", "tiny.png", "img2.png", "--calib", "calib.json"], S(PAIR, cp("pair/tiny.png")),
          err=("image_size1|size", "1x1|320x240")),
        C("image size differs from calibration", G, "160x120 image, 320x240 calibration",
          ["segments", "small.png", "img2.png", "--calib", "calib.json", "--points", "10,10", "--out", "f.png"],
          S(PAIR, cp("pair/small.png")), err=("image_size1|size", "160x120|320x240")),
        C("calib missing", G, "calibration does not exist", MATCH[:3] + ["--calib", "nope.json"], PAIR,
          err=("nope.json", "not found|no such|does not exist")),
        C("calib is a folder", G, "a folder given as calibration (issue: 'not found')",
          MATCH[:3] + ["--calib", "cdir.json"], S(PAIR, mkdir("cdir.json")), err=("cdir.json", "folder|directory")),
        C("calib .txt holding JSON", G, "unknown extension", MATCH[:3] + ["--calib", "c.txt"],
          S(PAIR, cp("pair/calib.json", "c.txt")), expect="either", err=("c.txt", r"\.json|\.yml|extension|YAML")),
        C("--out .txt", G, "bad extension", MATCH + ["--out", "m.txt"], PAIR, err=("--out", r"\.json")),
        C("--out parent is a file", G, "issue: 'File exists'", MATCH + ["--out", "img1.png/m.json"], PAIR,
          err=("--out|m.json|img1.png", "not a folder|is a file|not a directory")),
        C("--out is a folder", G, "an existing folder named m.json", MATCH + ["--out", "m.json"], S(PAIR, mkdir("m.json")),
          err=("--out|m.json", "folder|directory")),
        C("--out on a full disk", G, "m.json -> /dev/full", MATCH + ["--out", "m.json"],
          S(PAIR, symlink("m.json", "/dev/full")), err=("--out|m.json", "space|full")),
        C("--out overwrites the calibration", G, "--out calib.json: an input file",
          MATCH + ["--out", "calib.json"], PAIR, err=("--out|calib.json", "input|calib")),
        C("--figure overwrites an input image", G, "--figure img1.png: an input file",
          MATCH + ["--figure", "img1.png"], PAIR, err=("--figure|img1.png", "input|image 1|IMG1")),
        C("--figure .xyz", G, "issue: 'unknown or unsupported extension?'", MATCH + ["--figure", "f.xyz"], PAIR,
          err=("--figure", r"\.png|extension")),
        C("--figure without extension", G, "no suffix", MATCH + ["--figure", "fig"], PAIR,
          err=("--figure", r"\.png|extension")),
        C("--figure parent is a file", G, "issue: any file-system error reported as 'extension?'",
          MATCH + ["--figure", "img2.png/f.png"], PAIR, err=("--figure|f.png|img2.png", "not a folder|not a directory|is a file")),
        C("--figure is a folder", G, "an existing folder named f.png", MATCH + ["--figure", "f.png"],
          S(PAIR, mkdir("f.png")), err=("--figure|f.png", "folder|directory")),
        C("--figure on a full disk", G, "f.png -> /dev/full (issue: 'extension?')", MATCH + ["--figure", "f.png"],
          S(PAIR, symlink("f.png", "/dev/full")), err=("--figure|f.png", "space|full|write")),
        C("segments --out .xyz", G, "bad extension", ["segments", "img1.png", "img2.png", "--calib", "calib.json",
                                                       "--out", "s.xyz"], PAIR, err=("--out", r"\.png|extension")),
        C("segments --out parent is a file", G, "ENOTDIR", ["segments", "img1.png", "img2.png", "--calib", "calib.json",
                                                             "--out", "calib.json/s.png"], PAIR,
          err=("--out|s.png|calib.json", "not a folder|not a directory|is a file")),
        C("segments --out overwrites an input", G, "--out img2.png", ["segments", "img1.png", "img2.png", "--calib",
                                                                     "calib.json", "--out", "img2.png"], PAIR,
          err=("--out|img2.png", "input|image 2|IMG2")),
        C("demo --out onto a file", G, "DIR is a file", ["demo", "--out", "f"], write("f", "x"),
          err=("--out|f", "folder|directory|file")),
        C("synthetic DIR onto a file", G, "DIR is a file", ["synthetic", "f", "--views", "2", "--size", "64", "48"],
          write("f", "x"), err=("f|DIR", "folder|directory|file")),
        C("synthetic over an existing model", G, "DIR already holds a COLMAP model and images (silently replaced?)",
          ["synthetic", "old", "--views", "2", "--size", "64", "48"],
          S(cp("coll/model", "old/model"), cp("coll/images", "old/images")), expect="either",
          err=("old", "exists|--overwrite|not empty|already holds")),
    ]
    return out


def g_calib_json() -> list[Case]:
    G = "calib-json"
    out = []

    def cj(name, doc, mutate, expect="error", err=(), raw=False, check=FIG, argv=SEG_C):
        out.append(C(f"json {name}", G, doc, argv, S(PAIR, calib_variant(mutate, raw=raw)), expect=expect, err=err,
                     check=check))

    ident = lambda c: c  # noqa: E731
    cj("valid", "the fixture calibration", ident, "result")
    for k in ("K1", "K2", "R", "t"):
        cj(f"missing {k}", f"no key {k}", drop(k), err=(f"'{k}'", "missing"))
    cj("without image sizes", "sizes from the images", drop("image_size1", "image_size2"), "result")
    K = lambda fn: set_in(["K1"], fn)  # noqa: E731
    for name, val, err in [
        ("K1 3x4", lambda k: [r + [0.0] for r in k], ("K1", "3x3")),
        ("K1 2x2", [[1.0, 0.0], [0.0, 1.0]], ("K1", "3x3")),
        ("K1 flat 9", lambda k: [x for r in k for x in r], ("K1", "3x3")),
        ("K1 ragged", [[1, 2, 3], [4, 5], [6]], ("K1", "3x3|numbers")),
        ("K1 string", "abc", ("K1", "3x3|numbers|matrix")),
        ("K1 null", None, ("K1", "missing|3x3")),
        ("K1 number", 5, ("K1", "3x3")),
        ("K1 object", {"a": 1}, ("K1", "3x3|numbers")),
        ("K1 not upper triangular", lambda k: [k[0], [5.0, k[1][1], k[1][2]], k[2]], ("K1", "upper triangular")),
        ("K1 zero focal", lambda k: [[0.0, 0.0, k[0][2]], k[1], k[2]], ("K1", "focal")),
        ("K1 negative fx", lambda k: [[-k[0][0], 0.0, k[0][2]], k[1], k[2]], ("K1", "focal|positive")),
        ("K1 negative fy", lambda k: [k[0], [0.0, -k[1][1], k[1][2]], k[2]], ("K1", "focal|positive")),
        ("K1 last row 0 0 2", lambda k: [k[0], k[1], [0.0, 0.0, 2.0]], ("K1", r"last row|\[0, 0, 1\]")),
    ]:
        cj(name, f"K1 is {name[3:]}", K(val), err=err)
    cj("K1 NaN", "JSON NaN", K(lambda k: [[float("nan"), 0.0, k[0][2]], k[1], k[2]]), err=("K1", "finite"))
    cj("K1 Infinity", "JSON Infinity", K(lambda k: [[float("inf"), 0.0, k[0][2]], k[1], k[2]]), err=("K1", "finite"))
    cj("K1 1e999", "a number beyond float64", lambda c: (json.dumps(c).replace('"K1": [[250.0', '"K1": [[1e999')),
       err=("K1", "finite"), raw=True)
    cj("K1 cx 1e9", "issue: 'non-zero focal lengths' for a far principal point",
       K(lambda k: [[k[0][0], 0.0, 1e9], k[1], k[2]]), expect="either", err=("K1", "principal|cx|c_x"))
    cj("K1 fx 1e300", "absurd focal length", K(lambda k: [[1e300, 0.0, k[0][2]], k[1], k[2]]), expect="either",
       err=("K1",))
    cj("K1 booleans", "true/false entries", K(lambda k: [[True, False, False], [False, True, False], [False, False, True]]),
       expect="either", err=("K1",))
    cj("K1 numeric strings", '"250"', K(lambda k: [[str(x) for x in r] for r in k]), expect="either", err=("K1",))
    R = lambda v: set_in(["R"], v)  # noqa: E731
    cj("R not a rotation", "random matrix", R([[0.2, 0.5, 0.1], [0.3, 0.9, 0.4], [0.7, 0.1, 0.8]]), err=("'R'|R ", "rotation"))
    cj("R reflection", "det -1", R([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]), err=("'R'|R ", "rotation|det"))
    cj("R rounded to 5 decimals", "issue: real files are rounded; must be accepted", R(_rot5), "result")
    cj("R noise 1e-5", "orthonormal to 1e-5", R(lambda r: [[x + 1e-5 * ((i * 3 + j) % 3 - 1) for j, x in enumerate(row)]
                                                         for i, row in enumerate(r)]), "result")
    cj("R scaled by 2", "clear non-rotation", R(lambda r: [[2 * x for x in row] for row in r]), err=("'R'|R ", "rotation"))
    cj("R zeros", "clear non-rotation", R([[0.0] * 3] * 3), err=("'R'|R ", "rotation"))
    cj("R 3x4", "shape", R(lambda r: [row + [0.0] for row in r]), err=("'R'", "3x3"))
    cj("R NaN", "NaN", R(lambda r: [[float("nan")] + row[1:] for row in r]), err=("'R'", "finite"))
    t = lambda v: set_in(["t"], v)  # noqa: E731
    cj("t length 4", "shape", t([1.0, 0, 0, 0]), err=("'t'", "3"))
    cj("t column", "[[x],[y],[z]]", t(lambda v: [[x] for x in v]), "result")
    cj("t string", "text", t("abc"), err=("'t'",))
    cj("t null", "null", t(None), err=("'t'",))
    cj("t zeros", "pure rotation", t([0.0, 0.0, 0.0]), "result")
    cj("t 1e300", "huge translation", t([1e300, 0.0, 1e300]), expect="either", err=("'t'|t ",))
    cj("t NaN", "NaN", t([float("nan"), 0.0, 1.0]), err=("'t'", "finite"))
    sz = lambda v: set_in(["image_size1"], v)  # noqa: E731
    for name, val, err, exp in [("0 240", [0, 240], ("image_size1", "positive"), "error"),
                                ("-320 240", [-320, 240], ("image_size1", "positive"), "error"),
                                ("320.5 240", [320.5, 240], ("image_size1", "integer"), "error"),
                                ("string", "320x240", ("image_size1", "width, height|two"), "error"),
                                ("one number", [320], ("image_size1", "width, height|two"), "error"),
                                ("three numbers", [320, 240, 3], ("image_size1", "width, height|two"), "error"),
                                ("null", None, (), "result"),
                                ("1e20", [1e20, 1e20], ("image_size1", "320x240|image"), "error"),
                                ("640 480 (mismatch)", [640, 480], ("image_size1", "640"), "error")]:
        cj(f"image_size1 {name}", "image size", sz(val), exp, err)
    d1 = lambda v: (lambda c: {**c, "dist1": v})  # noqa: E731
    cj("dist1 length 3", "3 coefficients", d1([0.1, 0.0, 0.0]), err=("dist1", "4, 5, 8"))
    cj("dist1 strings", "text", d1(["a", "b", "c", "d"]), err=("dist1",))
    cj("dist1 NaN", "NaN", d1([float("nan"), 0, 0, 0]), err=("dist1", "finite"))
    cj("dist1 zeros", "no distortion", d1([0.0] * 5), "result")
    cj("dist1 k1 0.1", "mild distortion", d1([0.1, 0.0, 0.0, 0.0]), "result")
    cj("dist1 14 coefficients", "full rational+thin prism+tilt", d1([0.01] * 14), "either", ("dist1",))
    out.append(C("json dist1 k1 -5", G, "issue: distortion not invertible over the image; matches labelled on-segment",
                 ["match", "img1.png", "img2.png", "--calib", "c.json", "--out", "m.json"],
                 S(PAIR, calib_variant(lambda c: {**c, "dist1": [-5.0, 0, 0, 0], "dist2": [-5.0, 0, 0, 0]})),
                 expect="either", err=("dist1|k1|distortion", "invert|monoton|fold|map back"),
                 check=_round_trip_check))
    for name, text, err in [("top-level list", "[1, 2, 3]", ("top level|object",)),
                            ("top-level string", '"abc"', ("top level|object",)),
                            ("top-level null", "null", ("top level|object",)),
                            ("empty object", "{}", ("missing",)),
                            ("trailing comma", '{"K1": [1, 2, 3],}', ("c.json", "JSON")),
                            ("nested 100000 deep", '{"K1": ' + nested(100000) + "}", ("c.json", "deep|nest|recurs")),
                            ("K1 nested 100 deep", '{"K1": ' + nested(100) + "}", ("K1",))]:
        cj(name, name, lambda c, text=text: text, err=err, raw=True)
    cj("0-byte", "empty file", lambda c: "", err=("c.json", "JSON|empty"), raw=True)
    cj("BOM", "UTF-8 with a byte-order mark (Windows editors)", lambda c: "\ufeff" + json.dumps(c), "either",
       ("c.json", "BOM|UTF-8|encoding"), raw=True)
    out.append(C("json UTF-16", G, "UTF-16 file", SEG_C,
                 S(PAIR, write("c.json", lambda d, fix: json.dumps(base_calib(fix)).encode("utf-16"))),
                 err=("c.json", "UTF|text|encoding"), check=FIG))
    out.append(C("json garbage bytes", G, "random bytes", SEG_C, S(PAIR, write("c.json", bytes(range(256)) * 4)),
                 err=("c.json", "text|JSON|UTF")))
    cam = lambda c: {"K": c["K1"], "R": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "t": [0.0, 0, 0],  # noqa: E731
                     "image_size": [320, 240]}
    cam2 = lambda c: {"K": c["K2"], "R": c["R"], "t": c["t"], "image_size": [320, 240]}  # noqa: E731
    cj("cameras valid", "world poses per camera", lambda c: {"cameras": [cam(c), cam2(c)]}, "result")
    cj("cameras empty", "[]", lambda c: {"cameras": []}, err=("cameras", "two"))
    cj("cameras one", "one camera", lambda c: {"cameras": [cam(c)]}, err=("cameras", "two"))
    cj("cameras three", "three cameras", lambda c: {"cameras": [cam(c)] * 3}, err=("cameras", "two"))
    cj("cameras missing R", "cameras[1] without R", lambda c: {"cameras": [cam(c), drop("R")(cam2(c))]},
       err=(r"cameras\[1\]", "'R'"))
    cj("cameras string", "not a list", lambda c: {"cameras": "abc"}, err=("cameras", "list"))
    P = lambda c, R, t: [[sum(c["K1"][i][k] * R[k][j] for k in range(3)) for j in range(3)]  # noqa: E731
                         + [sum(c["K1"][i][k] * t[k] for k in range(3))] for i in range(3)]
    I3 = [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]
    cj("P1 P2 valid", "projection matrices", lambda c: {"P1": P(c, I3, [0, 0, 0]), "P2": P(c, c["R"], c["t"]),
                                                         "image_size1": [320, 240], "image_size2": [320, 240]}, "result")
    cj("P1 singular", "zeros", lambda c: {"P1": [[0.0] * 4] * 3, "P2": P(c, c["R"], c["t"])}, err=("P1",))
    cj("P1 3x3", "shape", lambda c: {"P1": I3, "P2": P(c, c["R"], c["t"])}, err=("P1", "3x4"))
    cj("P1 NaN", "NaN", lambda c: {"P1": [[float("nan")] * 4] * 3, "P2": P(c, c["R"], c["t"])}, err=("P1", "finite"))
    cj("world poses flat valid", "K1 R1 t1 K2 R2 t2", lambda c: {"K1": c["K1"], "R1": I3, "t1": [0, 0, 0], "K2": c["K2"],
                                                                 "R2": c["R"], "t2": c["t"]}, "result")
    cj("world poses R1 not rotation", "R1 scaled", lambda c: {"K1": c["K1"], "R1": [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]],
                                                              "t1": [0, 0, 0], "K2": c["K2"], "R2": c["R"], "t2": c["t"]},
       err=("R1", "rotation"))
    cj("OpenCV names in JSON", "M1 D1 M2 D2 R T", lambda c: {"M1": c["K1"], "M2": c["K2"], "D1": [0] * 5, "D2": [0] * 5,
                                                             "R": c["R"], "T": c["t"]}, "result")
    om = lambda rows, cols, data: {"type_id": "opencv-matrix", "rows": rows, "cols": cols, "dt": "d", "data": data}  # noqa: E731
    cj("opencv-matrix rows/cols mismatch", "rows 3 cols 4 with 9 numbers",
       lambda c: {**c, "K1": om(3, 4, [x for r in c["K1"] for x in r])}, err=("K1", "3x|rows|cols|shape|9"))
    cj("opencv-matrix data string", "data 'abc'", lambda c: {**c, "K1": om(3, 3, "abc")}, err=("K1",))
    cj("K shared", "one K for both", lambda c: {**drop("K1", "K2")(dict(c)), "K": c["K1"]}, "result")
    dino = ["segments", str(DINO / "dinoSR0001.png"), str(DINO / "dinoSR0002.png"), "--calib", "c.json", "--points",
            "320,240", "--out", "fig.png"]
    out.append(C("json dinoSparseRing world poses", G, "issue: real rotations orthonormal to 1.4e-6 must be accepted",
                 dino, write("c.json", lambda d, fix: (fix / "dino" / "calib_world.json").read_text()), expect="result",
                 check=FIG, extra_inputs=(DINO,)))
    out.append(C("json dinoSparseRing cameras", G, "issue: same, cameras layout", dino,
                 write("c.json", lambda d, fix: (fix / "dino" / "calib_cameras.json").read_text()), expect="result",
                 check=FIG, extra_inputs=(DINO,)))
    return out


def g_calib_cv() -> list[Case]:
    G = "calib-yaml-xml"
    out = []
    SEGY = lambda n: ["segments", "img1.png", "img2.png", "--calib", n, "--points", "160,120", "--out", "fig.png"]  # noqa: E731

    def cy(name, doc, expect="error", err=(), xml=False, raw=None, **changes):
        n = "c.xml" if xml else "c.yml"
        setup = write(n, raw) if raw is not None else yaml_variant(n, xml, **changes)
        out.append(C(f"{'xml' if xml else 'yml'} {name}", G, doc, SEGY(n), S(PAIR, setup), expect=expect, err=err,
                     check=FIG))

    out.append(C("yml as written by save_calibration", G, "round trip", SEGY("calib.yml"), S(PAIR, cp("pair/calib.yml")),
                 expect="result", check=FIG))
    out.append(C("xml as written by save_calibration", G, "round trip", SEGY("calib.xml"), S(PAIR, cp("pair/calib.xml")),
                 expect="result", check=FIG))
    out.append(C("yml.gz", G, "gzipped YAML", SEGY("c.yml.gz"),
                 S(PAIR, write("c.yml.gz", lambda d, fix: gzip.compress((fix / "pair" / "calib.yml").read_bytes()))),
                 expect="result", check=FIG))
    cy("valid", "hand-written OpenCV YAML", "result")
    cy("valid", "hand-written OpenCV XML", "result", xml=True)
    out.append(C("yaml extension", G, ".yaml", SEGY("c.yaml"), S(PAIR, yaml_variant("c.yaml")), expect="result", check=FIG))
    cy("missing M1", "no M1", err=("missing key 'M1'|'M1' .*missing|missing 'M1'",), M1=None)
    cy("missing T", "no T", err=("'T'|T ", "missing"), T=None)
    cy("missing R", "no R", err=("'R'", "missing"), xml=True, R=None)
    cy("M1 2x2", "shape", err=("M1", "3x3"), M1=mat(2, 2, [1, 0, 0, 1]))
    cy("M1 string", "text", err=("M1",), M1='"abc"')
    cy("R not a rotation", "random", err=("'R'|R ", "rotation"), R=mat(3, 3, [0.2, 0.5, 0.1, 0.3, 0.9, 0.4, 0.7, 0.1, 0.8]))
    cy("R rounded to 5 decimals", "issue: must be accepted", "result",
       R=lambda m: mat(3, 3, [round(x, 5) for x in m[3]]))
    cy("M1 NaN", ".nan", err=("M1", "finite"), M1=lambda m: mat(3, 3, [float("nan")] + m[3][1:]))
    cy("M1 1e400", "beyond float64", err=("M1", "finite"), M1=lambda m: mat(3, 3, ["1e400"] + m[3][1:]))
    cy("M1 negative focal", "fx < 0", err=("M1", "focal|positive"), M1=lambda m: mat(3, 3, [-m[3][0]] + m[3][1:]))
    cy("M1 rows/cols vs data", "rows 3 cols 3 with 8 numbers", err=("M1|c.yml",), M1=lambda m: mat(3, 3, m[3][:8]))
    cy("M1 rows/cols vs data", "rows 3 cols 3 with 8 numbers", err=("M1|c.xml",), xml=True,
       M1=lambda m: mat(3, 3, m[3][:8]))
    cy("M1 huge rows", "rows 100000000 cols 100000000", err=("M1|c.xml",), xml=True,
       M1=lambda m: mat(100000000, 100000000, m[3]))
    cy("D1 length 3", "1x3 distortion", err=("D1", "4, 5, 8"), D1=mat(1, 3, [0.1, 0, 0]))
    cy("image_width string", "image_width: abc", err=("image_width|width",), image_width='"abc"')
    cy("garbage", "random bytes", err=("c.yml", "parse|YAML|read"), raw=bytes(range(256)) * 4)
    cy("0-byte", "empty", err=("c.yml",), raw=b"")
    cy("header only", "%YAML:1.0 and nothing", err=("missing",), raw="%YAML:1.0\n---\n")
    cy("tab-indented junk", "broken YAML", err=("c.yml",), raw="%YAML:1.0\n---\nM1: !!opencv-matrix\n\trows: [\n")
    cy("BOM", "byte-order mark", "either", ("c.yml",), raw=lambda d, fix: "\ufeff" + cv_yaml(cv_entries(fix)))
    cy("nested 100000 deep", "a deep sequence", err=("c.yml", "deep|nest|parse"),
       raw="%YAML:1.0\n---\nM1: " + nested(100000) + "\n")
    cy("malformed", "unclosed tag", err=("c.xml",), xml=True, raw='<?xml version="1.0"?>\n<opencv_storage>\n<M1 type_id=')
    cy("0-byte", "empty", err=("c.xml",), xml=True, raw=b"")
    cy("nested 100000 deep", "deep elements", err=("c.xml", "deep|nest|parse"), xml=True,
       raw='<?xml version="1.0"?>\n<opencv_storage>\n' + "<a>" * 100000 + "1" + "</a>" * 100000 + "\n</opencv_storage>\n")
    cy("plain YAML (PyYAML style)", "no OpenCV header, nested lists", "either", ("c.yml",),
       raw=lambda d, fix: "\n".join(f"{k}: {json.dumps(v)}" for k, v in base_calib(fix).items()) + "\n")
    return out


def g_matches_file() -> list[Case]:
    G = "matches-file"
    out = []
    RM = "read_matches = _imp(P['read_matches'])\nreturn read_matches({!r})"

    def m(name, doc, fname, setup, expect="error", err=(), cats=("value", "type"), check=None):
        out.append(A(f"read_matches {name}", G, doc, RM.format(fname), expect=expect, err=err, setup=setup,
                     cats=cats, check=check))

    def jm(mutate):
        return write("x.json", lambda d, fix: mutate(json.loads((fix / "pair" / "m.json").read_text())))

    js = lambda fn: (lambda c: json.dumps(fn(c)))  # noqa: E731
    m("json", "as written by match --out", "m.json", cp("pair/m.json"), "result")
    m("npz", "as written by match --out", "m.npz", cp("pair/m.npz"), "result")
    m("csv", "issue: a traceback on a CSV", "m.csv", cp("pair/m.csv"), "either", ("m.csv", r"\.json|\.npz|CSV"))
    m("txt", "unknown extension", "m.txt", cp("pair/m.json", "m.txt"), "either", ("m.txt", r"\.json|extension"))
    m("missing", "no such file", "nope.json", None, err=("nope.json",), cats=("value", "type", "os"))
    m("folder", "a folder", "dir.json", mkdir("dir.json"), err=("dir.json", "folder|directory"),
      cats=("value", "type", "os"))
    m("0-byte json", "empty", "e.json", write("e.json", ""), err=("e.json", "JSON|empty"))
    m("0-byte npz", "empty", "e.npz", write("e.npz", b""), err=("e.npz", "empty|npz|zip"))
    m("truncated json", "half", "m.json", S(cp("pair/m.json"), truncate("m.json", 0.5)), err=("m.json", "JSON"))
    m("truncated npz", "half", "m.npz", S(cp("pair/m.npz"), truncate("m.npz", 0.5)), err=("m.npz", "zip|npz|truncat|corrupt"))
    m("garbage npz", "random bytes", "g.npz", write("g.npz", bytes(range(256)) * 4), err=("g.npz",))
    for k in ("matches", "meta", "labels", "distances"):
        m(f"json without {k}", f"no key {k}", "x.json", jm(js(drop(k))), err=(k, "missing|key"))
    m("json matches odd", "3 numbers", "x.json", jm(js(lambda c: {**c, "matches": [1, 2, 3]})), err=("matches",))
    m("json matches strings", "text", "x.json", jm(js(lambda c: {**c, "matches": [["a", "b"]]})), err=("matches",))
    m("json keypoints1 ragged", "ragged", "x.json", jm(js(lambda c: {**c, "keypoints1": [[1, 2], [3]]})),
      err=("keypoints1",))
    m("json top-level list", "a list", "x.json", write("x.json", "[1, 2]"), err=("x.json", "object"))
    m("json nested 100000 deep", "recursion", "x.json", write("x.json", nested(100000)),
      err=("x.json", "deep|nest|recurs"))
    m("json indices out of range", "matches beyond the keypoints", "x.json",
      jm(js(lambda c: {**c, "matches": [[10 ** 6, 0]] + c["matches"][1:]})), "either", ("matches", "range"))
    m("json other format", "meta.format 'other'", "x.json",
      jm(js(lambda c: {**c, "meta": {**c["meta"], "format": "other"}})), "either", ("format",))
    m("json format_version 99", "future version", "x.json",
      jm(js(lambda c: {**c, "meta": {**c["meta"], "format_version": 99}})), "either", ("version",))
    m("json BOM", "byte-order mark", "x.json", jm(lambda c: "\ufeff" + json.dumps(c)), "either", ("x.json", "BOM|UTF"))

    def npz(**arrays):
        def step(d, fix):
            import numpy as np

            with np.load(fix / "pair" / "m.npz") as z:
                a = {k: z[k] for k in z.files}
            for k, v in arrays.items():
                if v is None:
                    a.pop(k)
                else:
                    a[k] = v
            np.savez(d / "x.npz", **a)
        return step

    m("npz without meta", "no meta", "x.npz", npz(meta=None), err=("meta",))
    m("npz meta not JSON", "meta 'abc'", "x.npz", npz(meta="abc{"), err=("meta", "JSON"))
    m("npz without matches", "no matches", "x.npz", npz(matches=None), err=("matches",))

    def pickled(d, fix):
        import numpy as np

        np.savez(d / "x.npz", meta=np.array([{"a": 1}], dtype=object), matches=np.zeros((0, 2)))
    m("npz object array", "needs allow_pickle", "x.npz", pickled, err=("x.npz|meta|pickle",))
    return out


def g_pairs() -> list[Case]:
    G = "pairs-file"
    out = []

    def pc(name, doc, content, expect="error", err=(), check=None):
        out.append(C(f"pairs {name}", G, doc, COLMAP + ["--pairs", "pairs.txt"], S(COLL, write("pairs.txt", content)),
                     expect=expect, err=err, check=check or check_db("db.db", 4), mutable=DB_MUT))

    pc("empty file", "issue: accepted silently", "", err=("pairs.txt", "no pairs|empty"))
    pc("comments only", "nothing but comments", "# nothing\n\n", err=("pairs.txt", "no pairs|empty"))
    pc("unknown image", "a name not in the model", "view_000.png nope.png\n", err=("pairs.txt:1", "nope.png"))
    pc("self pair", "image paired with itself", "view_000.png view_000.png\n", err=("pairs.txt:1", "itself"))
    pc("one column", "one name per line", "view_000.png\n", err=("pairs.txt:1", "name1 name2"))
    pc("garbage bytes", "random bytes", bytes(range(256)) * 4, err=("pairs.txt", "UTF|text|decode"))
    pc("duplicates", "same pair twice, both orders", "view_000.png view_001.png\nview_001.png view_000.png\n", "result")
    pc("three columns", "hloc-style extra column", "view_000.png view_001.png 0.9\n", "result")
    pc("CRLF", "Windows line endings", "view_000.png view_001.png\r\nview_001.png view_002.png\r\n", "result")
    out.append(C("pairs missing file", G, "--pairs does not exist", COLMAP + ["--pairs", "nope.txt"], COLL,
                 err=("nope.txt", "not found|no such|does not exist"), mutable=DB_MUT))
    out.append(C("pairs is a folder", G, "--pairs is a folder", COLMAP + ["--pairs", "pdir"], S(COLL, mkdir("pdir")),
                 err=("pdir", "folder|directory"), mutable=DB_MUT))
    return out


def g_poses() -> list[Case]:
    G = "poses-json"
    out = []

    def pj(name, doc, mutate, expect="error", err=(), raw=False, check=None, argv=COLMAP_P, **kw):
        out.append(C(f"poses {name}", G, doc, argv, S(COLL, poses_variant(mutate, raw=raw)), expect=expect, err=err,
                     check=check or check_db("db.db"), mutable=DB_MUT, **kw))

    im = lambda i, k, v: set_in(["images", i, k], v)  # noqa: E731
    pj("valid", "the fixture poses", lambda c: c, "result")
    pj("one image", "issue: accepted silently", lambda c: {"images": c["images"][:1]}, err=("image", "two|2|at least"))
    pj("empty list", "no images", lambda c: {"images": []}, err=("images", "non-empty|empty"))
    pj("bare list", "top level is the list", lambda c: c["images"], "result")
    pj("images dict", "not a list", lambda c: {"images": {"a": 1}}, err=("images", "list"))
    pj("item number", "an image is 5", lambda c: {"images": [5] + c["images"][1:]}, err=("image 0", "object"))
    for k in ("name", "K", "R", "t", "width", "height"):
        pj(f"missing {k}", f"image 1 without {k}", drop_in_image(1, k), err=("image 1", f"missing.*{k}"))
    pj("K negative focal", "issue: accepted silently", im(1, "K", [[-125.0, 0, 79.5], [0, 125.0, 59.5], [0, 0, 1]]),
       err=("image 1|view_001", "focal|positive"))
    pj("K 2x2", "shape", im(1, "K", [[1.0, 0], [0, 1.0]]), err=("image 1|view_001", "K", "3, 3|3x3"))
    pj("K string", "text", im(1, "K", "abc"), err=("image 1|view_001", "K"))
    pj("K NaN", "NaN", im(1, "K", [[float("nan"), 0, 79.5], [0, 125.0, 59.5], [0, 0, 1]]), err=("K", "finite"))
    pj("R not a rotation", "scaled", im(1, "R", [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]]), err=("R", "rotation"))
    pj("R rounded to 5 decimals", "issue: must be accepted",
       lambda c: {"images": [{**v, "R": _rot5(v["R"])} for v in c["images"]]}, "result")
    pj("R reflection", "det -1", im(1, "R", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]), err=("R", "rotation|det"))
    pj("t length 2", "shape", im(1, "t", [1.0, 2.0]), err=("image 1|view_001", "t", "3"))
    pj("t NaN", "NaN", im(1, "t", [float("nan"), 0, 0]), err=("t", "finite"))
    for v, err in [(0, ("width|image_size", "positive")), ("abc", ("width",)), (1.5, ("width", "integer")),
                   (-1, ("width|image_size", "positive")), (None, ("width",)),
                   (320, ("view_001", "320|160"))]:
        pj(f"width {v}", "bad width", im(1, "width", v), err=err)
    pj("image not in folder", "a name missing on disk", im(1, "name", "nope.png"), err=("nope.png", "missing"))
    pj("duplicate names", "listed twice", im(1, "name", "view_000.png"), err=("view_000.png", "twice"))
    pj("name outside the folder", "../ path", im(1, "name", "../images/view_001.png"), "either", ("name|outside",))
    pj("name is a number", "5", im(1, "name", 5), err=("5",))
    pj("dist length 3", "3 coefficients", im(1, "dist", [0.1, 0, 0]), err=("dist", "4, 5|8"))
    pj("depth_range 5 1", "zmin > zmax", im(1, "depth_range", [5, 1]), err=("depth_range", "zmin < zmax"))
    pj("depth_range string", "text", im(1, "depth_range", "abc"), err=("depth_range",))
    pj("extra keys", "unknown fields ignored", im(1, "comment", "hello"), "result")
    for name, text, err in [("invalid JSON", '{"images": [', ("p.json", "JSON|cannot be read|Expecting")),
                            ("0-byte", "", ("p.json",)),
                            ("nested 100000 deep", '{"images": ' + nested(100000) + "}", ("p.json", "deep|nest|recurs"))]:
        pj(name, name, lambda c, text=text: text, err=err, raw=True)
    out.append(C("poses garbage bytes", G, "random bytes", COLMAP_P, S(COLL, write("p.json", bytes(range(256)) * 4)),
                 err=("p.json", "text|UTF|read"), mutable=DB_MUT))
    pj("BOM", "byte-order mark", lambda c: "\ufeff" + json.dumps(c), "either", ("p.json", "BOM|UTF"), raw=True)
    dino = ["colmap", "poses.json", str(DINO), "--database", "db.db", "--pairs", "pairs.txt", "--max-features", "1000"]
    out.append(C("poses dinoSparseRing", G, "issue: real rotations (orthonormal to 1.4e-6) refused", dino,
                 S(cp("dino/poses.json"), cp("dino/pairs.txt")), expect="result", check=check_db("db.db", 16),
                 extra_inputs=(DINO,), mutable=DB_MUT, timeout=180))
    out.append(C("poses dinoSparseRing rounded", G, "issue: rotations rounded to 5 decimals", dino,
                 S(write("poses.json", lambda d, fix: json.dumps(
                     {"images": [{**v, "R": _rot5(v["R"])} for v in json.loads((fix / "dino" / "poses.json").read_text())["images"]]})),
                   cp("dino/pairs.txt")), expect="result", check=check_db("db.db", 16), extra_inputs=(DINO,),
                 mutable=DB_MUT, timeout=180))
    return out


def g_colmap_model() -> list[Case]:
    G = "colmap-model"
    out = []
    MT = S(cp("coll/images", "images"), cp("coll/model_txt", "model"))

    def mc(name, doc, setup, expect="error", err=(), check=None, **kw):
        out.append(C(f"model {name}", G, doc, COLMAP, setup, expect=expect, err=err,
                     check=check or check_db("db.db", 4), mutable=DB_MUT, **kw))

    def rm(name):
        return lambda d, fix: (d / name).unlink()

    mc("binary", "the fixture model", COLL, "result")
    mc("text", "the same model as text", MT, "result")
    mc("missing images.bin", "no images file", S(COLL, rm("model/images.bin")), err=("model", "images.bin|no COLMAP model"))
    mc("missing cameras.bin", "no cameras file", S(COLL, rm("model/cameras.bin")), err=("model|cameras", "cameras"))
    mc("missing points3D.bin", "no points file", S(COLL, rm("model/points3D.bin")), "either", ("points3D",))
    mc("missing frames.bin and rigs.bin", "an older COLMAP model (no rigs, frames)",
       S(COLL, rm("model/frames.bin"), rm("model/rigs.bin")), "either", ("frames|rigs",))
    mc("0-byte points3D.bin", "issue: 110 s and 4 GB before it fails", S(COLL, write("model/points3D.bin", b"")),
       err=("points3D",), mem_gb=2.0, timeout=45, resource_case=True)
    mc("0-byte images.bin", "empty", S(COLL, write("model/images.bin", b"")), err=("images",), mem_gb=2.0, timeout=45,
       resource_case=True)
    mc("0-byte cameras.bin", "empty", S(COLL, write("model/cameras.bin", b"")), err=("cameras",), mem_gb=2.0, timeout=45,
       resource_case=True)
    for f in ("images", "cameras", "points3D", "frames", "rigs"):
        mc(f"truncated {f}.bin", "half the bytes", S(COLL, truncate(f"model/{f}.bin", 0.5)), err=(f,), mem_gb=2.0,
           timeout=45, resource_case=True)
    mc("garbage images.bin", "random bytes", S(COLL, write("model/images.bin", bytes(range(256)) * 16)),
       err=("images",), mem_gb=2.0, timeout=45, resource_case=True)
    mc("images.bin huge count", "claims 2^62 images", S(COLL, write("model/images.bin",
                                                                    (2 ** 62).to_bytes(8, "little") + b"\0" * 64)),
       err=("images",), mem_gb=2.0, timeout=45, resource_case=True)
    mc("images.txt junk line", "a line of junk", S(MT, edit("model/images.txt", lambda s: s + "junk line here\n")),
       err=("images",))
    mc("cameras.txt unknown model", "FOO camera model", S(MT, edit("model/cameras.txt", lambda s: s.replace("PINHOLE", "FOO"))),
       err=("cameras|FOO|model",))
    mc("cameras.txt negative focal", "fx < 0",
       S(MT, edit("model/cameras.txt", lambda s: re.sub(r"(?m)^(1 PINHOLE 160 120) (\S+)", r"\1 -\2", s))),
       err=("focal|positive",))
    mc("cameras.txt width mismatch", "camera says 320x240, images are 160x120",
       S(MT, edit("model/cameras.txt", lambda s: s.replace("PINHOLE 160 120", "PINHOLE 320 240"))),
       err=("view_00", "160x120|320x240"))
    mc("points3D.txt junk", "a line of junk", S(MT, edit("model/points3D.txt", lambda s: s + "1 2 junk\n")),
       err=("points3D",))
    mc("images.txt header only", "no registered images",
       S(MT, edit("model/images.txt", lambda s: "\n".join(ln for ln in s.splitlines() if ln.startswith("#")) + "\n")),
       err=("no registered images|no images",))
    mc("empty folder", "model folder holds nothing", S(cp("coll/images", "images"), mkdir("model")),
       err=("model", "no COLMAP model|images.bin"))
    out.append(C("poses JSON over EXIF-tagged JPEGs", G, "issue: cv2.imread turns a tagged picture away from its pose "
                 "(refused: 'image is 120x160, but its camera says 160x120')",
                 ["colmap", "poses.json", "images", "--database", "db.db"], S(COLL, phone_jpegs()), expect="result",
                 check=check_db("db.db", 4), mutable=DB_MUT))
    out.append(C("model folder missing", G, "no such folder", ["colmap", "nope", "images", "--database", "db.db"],
                 COLL, err=("nope", "does not exist|not found")))
    out.append(C("model is images.bin", G, "a model file instead of its folder",
                 ["colmap", "model/images.bin", "images", "--database", "db.db"], COLL,
                 err=("images.bin", "folder|poses|JSON")))
    return out


def g_colmap_state() -> list[Case]:
    G = "colmap-state"
    out = []
    HALF = S(COLL, cp("coll/half.db", "db.db"), cp("coll/half.db.features", "db.db.features"),
             cp("coll/pairs_all.txt", "pairs_all.txt"))
    DONE = S(COLL, cp("coll/done.db", "db.db"), cp("coll/done.db.features", "db.db.features"))
    RES = COLMAP + ["--resume", "--pairs", "pairs_all.txt"]

    def st(name, doc, argv, setup, expect="error", err=(), check=None, **kw):
        kw.setdefault("mutable", DB_MUT)
        out.append(C(name, G, doc, argv, setup, expect=expect, err=err, check=check, **kw))

    st("--triangulate into the input model", "issue: input images.bin, points3D.bin, frames.bin replaced",
       COLMAP + ["--triangulate", "model"], COLL, err=("--triangulate|model", "input|model|same|overwrite"))
    st("--triangulate into the image folder", "writes a model among the images",
       COLMAP + ["--triangulate", "images"], COLL, "either", ("--triangulate|images", "image|input"),
       leftovers=("images/*.bin", "images/*.txt"))
    st("--triangulate onto a file", "issue: 'File exists'", COLMAP + ["--triangulate", "tri"], S(COLL, write("tri", "x")),
       err=("--triangulate|tri", NOT_FE + r".*(is a file|not a folder|not a directory)"))
    st("--triangulate into a non-empty folder", "a folder holding other files", COLMAP + ["--triangulate", "tri"],
       S(COLL, write("tri/keep.txt", "mine\n")), "either", ("--triangulate|tri", "empty|exists"))
    st("--triangulate valid", "normal run", COLMAP + ["--triangulate", "tri"], COLL, "result",
       check=all_of(check_db("db.db", 4), check_files("tri/images.bin", "tri/points3D.bin")))
    st("--cache onto a file", "issue: 'File exists'", COLMAP + ["--cache", "cf"], S(COLL, write("cf", "x")),
       err=("--cache|cf", NOT_FE + r".*(is a file|not a folder|not a directory)"))
    st("--cache nested new folder", "parents created", COLMAP + ["--cache", "a/b/c"], COLL, "result",
       check=check_db("db.db", 4), mutable=DB_MUT + ("a/*",))
    st("--database is an input image", "--overwrite onto images/view_000.png",
       ["colmap", "model", "images", "--database", "images/view_000.png", "--overwrite"], COLL,
       err=("database|view_000.png", "image|input"))
    st("--database is the poses JSON", "--overwrite onto the input poses.json",
       ["colmap", "poses.json", "images", "--database", "poses.json", "--overwrite"], COLL,
       err=("database|poses.json", "input|model|poses"))
    st("--database inside the model, onto images.bin", "--overwrite model/images.bin",
       ["colmap", "model", "images", "--database", "model/images.bin", "--overwrite"], COLL,
       err=("database|images.bin", "input|model"))
    st("--database exists", "no --resume or --overwrite", COLMAP, DONE, err=("db.db", "--overwrite", "--resume"))
    st("--database is a folder", "folder", COLMAP[:-1] + ["dbdir"], S(COLL, mkdir("dbdir")), err=("dbdir", "folder"))
    st("--database folder missing", "parent missing", COLMAP[:-1] + ["no/such/db.db"], COLL,
       err=("no/such", "does not exist"))
    st("--resume without database", "nothing to resume", COLMAP + ["--resume"], COLL, err=("db.db", "does not exist"))
    st("--resume on a text file", "issue: a traceback", COLMAP + ["--resume"], S(COLL, write("db.db", "hello\n" * 50)),
       err=("db.db", "SQLite|database|not a"))
    st("--resume on a 0-byte file", "an empty file", COLMAP + ["--resume"], S(COLL, write("db.db", b"")),
       err=("db.db", "empty|SQLite|not a .*database"))
    st("--resume on a truncated database", "half of a database", COLMAP + ["--resume"],
       S(DONE, truncate("db.db", 0.5)), err=("db.db", "SQLite|corrupt|malformed|not a"))
    st("--resume on a database of other images", "the big collection's database", COLMAP + ["--resume"],
       S(COLL, cp("big/full.db", "db.db")), err=("db.db", "other images"))
    st("--resume same settings", "all pairs already there", COLMAP + ["--resume"], DONE, "result",
       check=all_of(check_db("db.db", 4, 6), check_stdout(r"6 already written")))
    st("--resume half with the rest", "3 of 6 pairs done", RES, HALF, "result", check=check_db("db.db", 4, 6))
    for extra, err in [(["--tol", "5"], ("tol",)), (["--ratio", "0.75"], ("ratio",)),
                       (["--constraint", "line"], ("constraint",)), (["--depth-range", "none"], ("depth",)),
                       (["--depth-range", "0.5", "50"], ("depth",))]:
        st(f"--resume with {' '.join(extra)}", "issue: two settings mixed in one database, silently",
           RES + extra, HALF, err=err + ("changed|differ|other|was|database",), check=check_db("db.db", 4))
    st("--resume with --max-features 100", "other keypoints", RES + ["--max-features", "100"], HALF,
       err=("keypoints|features|max-features",))
    st("--resume with --detector orb", "other detector", RES + ["--detector", "orb"], HALF,
       err=("keypoints|features|detector",))

    def change_image(keep_mtime: bool):
        def step(d, fix):
            import numpy as np
            import cv2  # noqa: F401  (the venv has it)

            p = d / "images" / "view_001.png"
            st_ = p.stat()
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(p), np.ascontiguousarray(img[:, ::-1]))  # same size, other content
            if keep_mtime:
                os.utime(p, ns=(st_.st_atime_ns, st_.st_mtime_ns))
            else:
                t = time.time() + 5
                os.utime(p, (t, t))
        return step

    st("--resume after an image changed", "issue: exit 0, matches no longer agree with the poses",
       RES + ["--max-features", "100"],
       S(COLL, cp("coll/half100.db", "db.db"), cp("coll/half100.db.features", "db.db.features"),
         cp("coll/pairs_all.txt", "pairs_all.txt"), change_image(False)),
       err=("view_001", "changed"), check=check_keypoints_fresh("db.db", ("--max-features", "100")),
       mutable=DB_MUT + ("images/*",))
    def png0(d, fix):
        """images re-saved without compression (a file size that does not depend on the content)"""
        import cv2

        for p in (d / "images").glob("*.png"):
            cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_PNG_COMPRESSION, 0])

    def flip_same_size(d, fix):
        """view_001.png flipped left-right, same file size and modification time"""
        import cv2
        import numpy as np

        p = d / "images" / "view_001.png"
        st_, size = p.stat(), p.stat().st_size
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), np.ascontiguousarray(img[:, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 0])
        if p.stat().st_size != size:
            raise RuntimeError("the re-saved image changed size; the case cannot test a size-only signature")
        os.utime(p, ns=(st_.st_atime_ns, st_.st_mtime_ns))

    out.append(Case("image changed, mtime and size kept", G, "the feature cache signature is size + mtime only",
                    [Run(argv=COLMAP, expect="result", check=check_db("db.db", 4, 6)), Run(action=flip_same_size),
                     Run(argv=COLMAP + ["--overwrite"], expect="result", check=check_keypoints_fresh("db.db"))],
                    setup=S(COLL, png0), mutable=DB_MUT + ("images/*",)))
    st("--overwrite", "replace a database", COLMAP + ["--overwrite"], DONE, "result", check=check_db("db.db", 4, 6))
    st("image folder missing", "no such folder", ["colmap", "model", "nope", "--database", "db.db"], COLL,
       err=("nope", "does not exist"))
    st("image folder is a file", "a file", ["colmap", "model", "poses.json", "--database", "db.db"], COLL,
       err=("poses.json", "is a file|not a folder|not a directory"))
    st("image missing in the folder", "view_002.png deleted", COLMAP, S(COLL, lambda d, f: (d / "images/view_002.png").unlink()),
       err=("view_002.png", "missing"))
    st("image unreadable", "view_002.png is random bytes", COLMAP,
       S(COLL, write("images/view_002.png", bytes(range(256)) * 8)), err=("view_002.png", "read|decode"))
    st("collection image 0-byte", "view_002.png is empty", COLMAP, S(COLL, write("images/view_002.png", b"")),
       err=("view_002.png", "read|decode|empty"))
    st("image wrong size", "view_002.png is 320x240", COLMAP, S(COLL, cp("pair/img1.png", "images/view_002.png")),
       err=("view_002.png", "320x240|160x120"))
    st("two resumes at once", "issue: a traceback", RES, HALF, "either", ("db.db", "in use|locked|another|busy"),
       check=check_db("db.db", 4))
    out[-1].runs[0].copies = 2
    out[-1].post = post_db("db.db", 4)
    st("two new runs at once", "same new database from two runs", COLMAP, COLL, "either",
       ("db.db", "exists|in use|locked|another"), check=check_db("db.db", 4))
    out[-1].runs[0].copies = 2
    out[-1].post = post_db("db.db", 4)
    return out


def g_feature_cache() -> list[Case]:
    G = "feature-cache"
    out = []
    CACHED = S(COLL, cp("coll/done.db.features", "db.db.features"))

    def npz0(d):
        return sorted((d / "db.db.features").glob("view_000*.npz"))[0]

    def trunc(frac):
        def step(d, fix):
            p = npz0(d)
            b = p.read_bytes()
            p.write_bytes(b[:int(len(b) * frac)])
        return step

    def resave(**changes):
        def step(d, fix):
            import numpy as np

            p = npz0(d)
            with np.load(p) as z:
                a = {k: z[k] for k in z.files}
            for k, v in changes.items():
                if v is None:
                    a.pop(k)
                else:
                    a[k] = v(a[k]) if callable(v) else v
            with open(p, "wb") as f:
                np.savez(f, **a)
        return step

    def fc(name, doc, step, expect="result", err=(), check=None):
        out.append(C(f"cache {name}", G, doc, COLMAP, S(CACHED, step), expect=expect, err=err,
                     check=check or check_db("db.db", 4, 6), mutable=DB_MUT))

    fc("truncated npz", "issue: BadZipFile, never recomputed", trunc(0.5))
    fc("0-byte npz", "issue: EOFError, never recomputed", trunc(0.0))
    fc("garbage npz", "random bytes", lambda d, f: npz0(d).write_bytes(bytes(range(256)) * 8))
    fc("npz without descriptors", "signature valid, descriptors missing", resave(descriptors=None))
    fc("npz without pinhole", "signature valid, pinhole keypoints missing", resave(pinhole=None))
    fc("npz descriptors float64 wrong width", "signature valid, descriptors (N, 7)",
       resave(descriptors=lambda a: a[:, :7].astype("float64")), "either", ("view_000|cache",))
    fc("npz keypoints fewer than descriptors", "signature valid, inconsistent arrays",
       resave(keypoints=lambda a: a[:5]), "either", ("view_000|cache",))
    fc("npz of another image", "view_001's features under view_000's name (stale signature)",
       lambda d, f: shutil.copy2(sorted((d / "db.db.features").glob("view_001*.npz"))[0], npz0(d)),
       check=all_of(check_db("db.db", 4, 6), check_keypoints_fresh("db.db")))
    return out


def g_signals() -> list[Case]:
    G = "signals"
    out = []
    V = ["-v"]
    FEAT = ("line", r"features \[")
    PAIRS = ("line", r"pairs \[")
    RESUME = Run(argv=COLMAP + ["--resume"], expect="result", check=check_db("db.db", 8, 28), timeout=180)
    RERUN = Run(argv=COLMAP + ["--overwrite"], expect="result", check=check_db("db.db", 8, 28), timeout=180)

    def sg(name, doc, setup, argv, sig, trig, group=False, then=(), slow=None, post=None, timeout=180, **kw):
        runs = [Run(argv=argv, expect="either", signal=(sig, trig, group), slow=slow or {}, timeout=timeout, **kw)]
        runs += list(then)
        out.append(Case(f"{signal.Signals(sig).name} {name}", G, doc, runs, setup=setup,
                        mutable=DB_MUT + ("tri", "tri/*"), post=post or post_db("db.db", 8), exclusive=True))

    W2 = COLMAP + ["--workers", "2"] + V
    W1 = COLMAP + V
    sg("--workers 2 during features", "issue: workers and the resource tracker stay alive", BIG, W2,
       signal.SIGTERM, FEAT)
    sg("--workers 2 during features", "issue: workers stay alive blocked on a pipe; then a rerun", BIG, W2,
       signal.SIGKILL, FEAT, then=[RERUN])
    sg("--workers 2 during pairs", "whole pairs only; then --resume", BIG_CACHED, W2, signal.SIGTERM, PAIRS,
       then=[RESUME])
    sg("--workers 2 during pairs", "then --resume", BIG_CACHED, W2, signal.SIGKILL, PAIRS, then=[RESUME])
    sg("--workers 2 during pairs (Ctrl-C)", "SIGINT to the process group; then --resume", BIG_CACHED, W2,
       signal.SIGINT, PAIRS, group=True, then=[RESUME])
    sg("--workers 1 during pairs (Ctrl-C)", "then --resume", BIG_CACHED, W1, signal.SIGINT, PAIRS, group=True,
       then=[RESUME])
    sg("--workers 1 during pairs", "then --resume", BIG_CACHED, W1, signal.SIGTERM, PAIRS, then=[RESUME])
    slow_db = {"pycolmap:Database.write_keypoints": 0.4}
    sg("while the database is prepared", "issue: .DB.PID.partial and -shm/-wal never cleaned; then a rerun",
       BIG_CACHED, W1, signal.SIGKILL, ("file", "*.partial", 0.2), slow=slow_db, then=[RERUN])
    sg("while the database is prepared", "issue: .partial left", BIG_CACHED, W1, signal.SIGTERM, ("file", "*.partial", 0.2),
       slow=slow_db)
    sg("while the database is prepared (Ctrl-C)", "SIGINT", BIG_CACHED, W1, signal.SIGINT, ("file", "*.partial", 0.2),
       group=True, slow=slow_db)
    slow_tri = {"pycolmap:triangulate_points": 4.0}
    TRI = COLMAP + ["--triangulate", "tri"] + V
    SMALL = COLL

    def tri_post(ctx):
        t = ctx.d / "tri"
        found = []
        if t.exists() and not (t / "points3D.bin").exists() and not (t / "points3D.txt").exists():
            found.append(("leftover", "an incomplete triangulation folder 'tri' remains"))
        return found + (post_db("db.db", 4)(ctx))

    for sig, grp in ((signal.SIGINT, True), (signal.SIGTERM, False)):
        out.append(Case(f"{sig.name} during --triangulate", G, "issue: an empty OUT and OUT.partial remain",
                        [Run(argv=TRI, expect="either", signal=(sig, ("line", r"^database: ", 1.5), grp), slow=slow_tri,
                             timeout=120)], setup=SMALL, mutable=DB_MUT + ("tri", "tri/*"), post=tri_post,
                        leftovers=("tri.partial*", ".tri*"), exclusive=True))
    out.append(Case("SIGKILL during --triangulate", G, "then the same command with --resume",
                    [Run(argv=TRI, expect="either", signal=(signal.SIGKILL, ("line", r"^database: ", 1.5), False),
                         slow=slow_tri, timeout=120),
                     Run(argv=COLMAP + ["--resume", "--triangulate", "tri"], expect="result",
                         check=check_files("tri/points3D.bin"))],
                    setup=SMALL, mutable=DB_MUT + ("tri", "tri/*"), post=tri_post,
                    leftovers=("tri.partial*", ".tri*"), exclusive=True))
    sg("--scheduler local:2 during pairs", "Dask workers and nannies", BIG_CACHED,
       COLMAP + ["--scheduler", "local:2"] + V, signal.SIGTERM, PAIRS, post_signal_timeout=30)
    return out


def g_api_geometry() -> list[Case]:
    G = "api-geometry"
    out = []

    def ag(name, doc, code, expect="error", err=(), check=None, **kw):
        out.append(A(name, G, doc, code, expect=expect, err=err, check=check, **kw))

    ag("TwoViewGeometry valid", "", "geom()", "result")
    for arg, val, err, exp in [
        ("K1", "None", ("K1",), "error"), ("K1", "'abc'", ("K1",), "error"),
        ("K1", "[[1, 2], [3, 4]]", ("K1", r"\(3, 3\)|3x3"), "error"), ("K1", "np.zeros((3, 3))", ("K1",), "error"),
        ("K1", "np.where(np.eye(3) > 0, np.nan, K)", ("K1", "finite"), "error"),
        ("K1", "K * np.inf", ("K1", "finite"), "error"), ("K1", "K.astype(complex)", ("K1", "real"), "error"),
        ("K1", "np.array([[1, 'a', 3]] * 3, dtype=object)", ("K1",), "error"),
        ("K1", "[[100, 0, 79.5], [0, 100], [0, 0, 1]]", ("K1",), "error"),
        ("K1", "np.diag([-100.0, 100.0, 1.0]) + [[0, 0, 79.5], [0, 0, 59.5], [0, 0, 0]]", ("K1", "focal|positive"), "error"),
        ("K1", "np.diag([100.0, -100.0, 1.0]) + [[0, 0, 79.5], [0, 0, 59.5], [0, 0, 0]]", ("K1", "focal|positive"), "error"),
        ("K1", "np.array([[100.0, 0, 1e9], [0, 100.0, 59.5], [0, 0, 1]])", ("K1", "principal|cx"), "either"),
        ("K1", "K.astype(int)", (), "result"), ("K1", "K.astype(np.float32)", (), "result"),
        ("R", "None", ("R",), "error"), ("R", "np.eye(3, 4)", ("R", r"\(3, 3\)|3x3"), "error"),
        ("R", "[[0.2, 0.5, 0.1], [0.3, 0.9, 0.4], [0.7, 0.1, 0.8]]", ("R", "rotation"), "error"),
        ("R", "np.diag([1.0, 1.0, -1.0])", ("R", "rotation|det"), "error"),
        ("R", "np.round(rot([1, 2, 3], 0.3), 5)", (), "result"),
        ("R", "rot([1, 2, 3], 0.3) + 1e-5", (), "result"),
        ("R", "rot([1, 2, 3], 0.3).astype(np.float32)", (), "result"),
        ("R", "2 * np.eye(3)", ("R", "rotation"), "error"), ("R", "np.full((3, 3), np.nan)", ("R", "finite"), "error"),
        ("t", "None", ("t",), "error"), ("t", "[1.0, 0, 0, 0]", ("t", r"\(3,\)|3"), "error"),
        ("t", "[np.nan, 0, 0]", ("t", "finite"), "error"), ("t", "[[1.0], [0], [0]]", (), "result"),
        ("t", "['a', 'b', 'c']", ("t",), "error"), ("t", "np.zeros(3)", (), "result"),
        ("t", "[1e308, 0, 1e308]", ("t",), "either"),
        ("image_size1", "(0, 10)", ("image_size1", "positive"), "error"),
        ("image_size1", "(-1, 5)", ("image_size1", "positive"), "error"),
        ("image_size1", "(10.5, 3)", ("image_size1", "integer"), "error"),
        ("image_size1", "'640x480'", ("image_size1",), "error"), ("image_size1", "None", ("image_size1",), "error"),
        ("image_size1", "(640,)", ("image_size1",), "error"), ("image_size1", "(True, 5)", ("image_size1",), "error"),
        ("image_size1", "(np.int64(160), np.int64(120))", (), "result"),
        ("image_size1", "(1e20, 1e20)", ("image_size1",), "either"),
    ]:
        ag(f"TwoViewGeometry {arg}={val[:40]}", f"{arg} = {val}", f"geom({arg}={val})", exp, err)
    ag("TwoViewGeometry missing image_size2", "keyword missing", "TwoViewGeometry(K, K, I3, T, image_size1=S)",
       err=("image_size2",))
    for val, err, exp in [("None", ("points1",), "error"), ("[]", (), "result"),
                          ("[[1, 2, 3]]", ("points1", r"\(N, 2\)"), "error"),
                          ("[[np.nan, 1]]", ("points1", "finite"), "error"), ("[[np.inf, 1]]", ("points1", "finite"), "error"),
                          ("[['a', 'b']]", ("points1",), "error"), ("[[1, 2]]", (), "result"),
                          ("[[1e308, 1e308]]", ("points1",), "either")]:
        ag(f"segments points={val}", "points1", f"geom().segments({val})", exp, err)
    for val, err in [("(5, 1)", ("depth_range", "zmin < zmax")), ("(-1, 5)", ("depth_range", ">= 0")),
                     ("(np.nan, 1)", ("depth_range", "NaN")), ("('a', 'b')", ("depth_range",)),
                     ("(1, 2, 3)", ("depth_range", "pair")), ("(np.ones(3), 5)", ("depth_range", "shape|scalar"))]:
        ag(f"segments depth_range={val}", "bad depth range", f"geom().segments(P1, {val})", err=err)
    ag("segments per-point depth_range", "arrays of N", "geom().segments(P1, (np.ones(len(P1)), 5 * np.ones(len(P1))))",
       "result")
    for val, err in [("-1", ("margin", ">= 0")), ("np.nan", ("margin",)), ("'a'", ("margin",))]:
        ag(f"segments margin={val}", "margin", f"geom().segments(P1, margin={val})", err=err)
    ag("transfer depths NaN", "", "geom().transfer(P1, np.nan)", err=("depths", "finite"))
    ag("transfer depths wrong shape", "", "geom().transfer(P1, np.ones(3))", err=("depths", "shape"))
    ag("from_world_poses R1 not rotation", "", "TwoViewGeometry.from_world_poses(K, 2 * I3, T, K, I3, T, "
                                               "image_size1=S, image_size2=S)", err=("R1", "rotation"))
    ag("from_world_poses t1 NaN", "", "TwoViewGeometry.from_world_poses(K, I3, [np.nan, 0, 0], K, I3, T, "
                                      "image_size1=S, image_size2=S)", err=("t1", "finite"))
    ag("from_projection_matrices singular", "", "TwoViewGeometry.from_projection_matrices(np.zeros((3, 4)), "
                                                "np.hstack([K, K @ T[:, None]]), image_size1=S, image_size2=S)",
       err=("P1",))
    ag("from_projection_matrices 3x3", "", "TwoViewGeometry.from_projection_matrices(K, K, image_size1=S, image_size2=S)",
       err=("P1", r"\(3, 4\)|3x4"))
    ag("from_projection_matrices NaN", "", "TwoViewGeometry.from_projection_matrices(np.full((3, 4), np.nan), "
                                           "np.full((3, 4), np.nan), image_size1=S, image_size2=S)", err=("P1", "finite"))
    ag("from_projection_matrices -P", "negated camera", "TwoViewGeometry.from_projection_matrices("
                                                         "-np.hstack([K, np.zeros((3, 1))]), np.hstack([K, K @ T[:, None]]), "
                                                         "image_size1=S, image_size2=S)", "result")
    ag("inverse of a pure rotation", "t = 0", "geom(t=np.zeros(3)).inverse().segments(P1).valid", "result")
    ag("classify tol=-1", "", "geom().segments(P1).classify(P2, -1)", err=("tol", ">= 0"))
    ag("distance wrong shape", "", "geom().segments(P1).distance(np.ones((3, 3)))", err=("points2",))
    return out


def _matches_some(v):
    n = v["len"] if isinstance(v, dict) and "len" in v else len(v) if isinstance(v, list) else 0
    return None if n > 0 else "no matches (expected some)"


def g_api_matcher() -> list[Case]:
    G = "api-matcher"
    out = []

    def am(name, doc, code, expect="error", err=(), check=None, **kw):
        out.append(A(name, G, doc, code, expect=expect, err=err, check=check, **kw))

    for val, err in [("geometry=None", ("geometry", "TwoViewGeometry")), ("geometry={}", ("geometry", "TwoViewGeometry")),
                     ("normType=99", ("normType",)), ("normType='l3'", ("normType",)),
                     ("tol=-1", ("tol", ">= 0")), ("tol=np.nan", ("tol",)), ("tol='2'", ("tol",)),
                     ("ratio=0", ("ratio", r"\(0, 1\]")), ("ratio=2", ("ratio",)), ("ratio=np.nan", ("ratio",)),
                     ("pad=-1", ("pad",)), ("pad=1.5", ("pad",)), ("constraint='foo'", ("constraint",)),
                     ("depth_range=(5, 1)", ("depth_range",))]:
        kw = val if val.startswith("geometry") else f"geometry=geom(), {val}"
        am(f"SegmentMatcher({val})", "constructor", f"SegmentMatcher({kw})", err=err)
    M = "SegmentMatcher(geom())"
    am("match valid", "float32 SIFT-like", f"{M}.match(D1, D2, kps(P1), kps(P2))", "result", check=check_api(_matches_some))
    am("match uint8 Hamming", "binary", "SegmentMatcher(geom(), 6).match(B1, B2, P1, P2)", "result",
       check=check_api(_matches_some))
    am("match queryDescriptors None", "cv2 returns None for no keypoints", f"{M}.match(None, D2, [], P2)", "either",
       ("queryDescriptors",))
    am("match empty", "(0, 128) both", f"{M}.match(np.zeros((0, 128), np.float32), np.zeros((0, 128), np.float32), [], [])",
       "result")
    am("match float64 beyond float32", "issue: 0 matches with only numpy's overflow warning",
       f"{M}.match(D1.astype(np.float64) * 1e39, D2.astype(np.float64) * 1e39, P1, P2)", "either",
       ("Descriptors", "float32"), check=all_of(check_api(_matches_some), check_no_warning))
    am("match float64 normal", "float64 within range", f"{M}.match(D1.astype(np.float64), D2.astype(np.float64), P1, P2)",
       "result", check=check_api(_matches_some))
    for val, err in [("np.where(D1 > 0.5, np.nan, D1)", ("queryDescriptors", "finite")),
                     ("np.where(D1 > 0.5, np.inf, D1)", ("queryDescriptors", "finite")),
                     ("D1.astype(np.int32)", ("queryDescriptors", "float32|uint8")),
                     ("D1[0]", ("queryDescriptors", "shape")), ("D1[None]", ("queryDescriptors", "shape")),
                     ("D1[:, :64]", ("width",)), ("B1", ("dtype",))]:
        am(f"match queryDescriptors={val[:30]}", "bad descriptors", f"{M}.match({val}, D2, P1, P2)", err=err)
    for val, err in [("P1[:10]", ("queryKeypoints", "rows|keypoints")), ("None", ("queryKeypoints",)),
                     ("[cv2.KeyPoint(float('nan'), 1.0, 5.0)] + kps(P1[1:])", ("queryKeypoints", "finite")),
                     ("kps(P1[:1]) + [tuple(p) for p in P1[1:]]", ("queryKeypoints",)),
                     ("['a'] * len(P1)", ("queryKeypoints",)), ("np.ones((len(P1), 3))", ("queryKeypoints", "shape"))]:
        am(f"match queryKeypoints={val[:30]}", "bad keypoints", f"import cv2\nreturn {M}.match(D1, D2, {val}, P2)", err=err)
    am("match NORM_HAMMING with float", "wrong norm", "SegmentMatcher(geom(), 6).match(D1, D2, P1, P2)",
       err=("HAMMING|uint8",))
    am("match NORM_L2 with uint8", "widened", f"{M}.match(B1, B2, P1, P2)", "result")
    am("match crossCheck", "both directions", "SegmentMatcher(geom(), crossCheck=True).match(D1, D2, P1, P2)", "result",
       check=check_api(_matches_some))
    for val, err in [("0", ("k", ">= 1")), ("-1", ("k", ">= 1")), ("1.5", ("k", "integer")), ("'2'", ("k", "integer")),
                     ("True", ("k", "integer"))]:
        am(f"knnMatch k={val}", "bad k", f"{M}.knnMatch(D1, D2, P1, P2, {val})", err=err)
    am("knnMatch k=5", "", f"{M}.knnMatch(D1, D2, P1, P2, 5)", "result")
    big = ("rng = np.random.default_rng(1)\n"
           "Q1 = rng.uniform([0, 0], [159, 119], (2000, 2)); Q2 = rng.uniform([0, 0], [159, 119], (2000, 2))\n"
           "E1 = rng.random((2000, 128), dtype=np.float32); E2 = rng.random((2000, 128), dtype=np.float32)\n")
    am("knnMatch k=10**6 on 2k x 2k", "issue: memory grows with N1 x k; cap k at the candidates (RLIMIT_AS 1.5 GB)",
       big + f"return {M}.knnMatch(E1, E2, Q1, Q2, 10**6)", "result", mem_gb=1.5, timeout=120, resource_case=True)
    am("knnMatch k=2**62", "k near the int64 limit (RLIMIT_AS 1.5 GB)", f"{M}.knnMatch(D1, D2, P1, P2, 2**62)", "either",
       ("k",), mem_gb=1.5, timeout=60, resource_case=True)
    for val, err, exp in [("-1", ("maxDistance", ">= 0"), "error"), ("np.nan", ("maxDistance",), "error"),
                          ("'x'", ("maxDistance",), "error"), ("np.inf", ("maxDistance",), "either"),
                          ("1.0", (), "result")]:
        am(f"radiusMatch maxDistance={val}", "radius", f"{M}.radiusMatch(D1, D2, P1, P2, {val})", exp, err)
    am("filter None", "no matches", f"{M}.filter(None, P1, P2)", "either", ("matches",))
    am("filter DMatch out of range", "queryIdx 10**6",
       f"import cv2\nreturn {M}.filter([cv2.DMatch(10**6, 0, 1.0)], P1, P2)", err=("index|range",))
    am("filter list of ints", "not DMatch", f"{M}.filter([1, 2, 3], P1, P2)", err=("matches|DMatch",))
    am("filter knn nested", "knnMatch output", f"m = {M}\nreturn m.filter(m.knnMatch(D1, D2, P1, P2, 2), P1, P2)", "result")
    am("filter junk mixed", "DMatch and str", f"import cv2\nreturn {M}.filter([cv2.DMatch(0, 0, 1.0), 'x'], P1, P2)",
       err=("matches|DMatch",))
    am("explain out of range", "trainIdx 10**6",
       f"import cv2\nreturn {M}.explain([cv2.DMatch(0, 10**6, 1.0)], P1, P2)", err=("index|range",))
    am("explain valid", "", f"m = {M}\nreturn m.explain(m.match(D1, D2, P1, P2), P1, P2)", "result")
    return out


def g_api_functions() -> list[Case]:
    G = "api-functions"
    out = []

    def af(name, doc, code, expect="error", err=(), check=None, **kw):
        out.append(A(name, G, doc, code, expect=expect, err=err, check=check, **kw))

    MD = "ep.match_descriptors(D1, D2, P1, P2, geom(){})"
    af("match_descriptors valid", "", MD.format(""), "result", check=check_api(lambda v: None if v[0]["shape"][0] else
                                                                                   "no matches"))
    for val, err in [(", norm='l3'", ("norm",)), (", pad=-1", ("pad",)), (", rng='abc'", ("rng|seed",)),
                     (", bucket_size=0", ("bucket_size",)), (", bucket_size=-1", ("bucket_size",)),
                     (", bucket_size='x'", ("bucket_size",)), (", ratio=0", ("ratio",)),
                     (", depth_range=(np.ones(3), 5)", ("depth_range",)), (", tol=np.inf", ("tol",))]:
        af(f"match_descriptors{val}", "bad option", MD.format(val), err=err)
    af("match_descriptors geometry None", "", "ep.match_descriptors(D1, D2, P1, P2, None)",
       err=("geometry", "TwoViewGeometry"))
    af("match_descriptors cross_check='yes'", "a truthy string", MD.format(", cross_check='yes'"), "either",
       ("cross_check",))
    af("match_descriptors pad=10**9", "a huge padding (RLIMIT_AS 1.5 GB)", MD.format(", pad=10**9"), "either", ("pad",),
       mem_gb=1.5, timeout=60, resource_case=True)
    af("match_descriptors float64 beyond float32", "issue: 0 matches, numpy overflow warning only",
       "ep.match_descriptors(D1.astype(np.float64) * 1e39, D2.astype(np.float64) * 1e39, P1, P2, geom())", "either",
       ("descriptors", "float32"), check=all_of(check_api(lambda v: None if v[0]["shape"][0] else "no matches"),
                                               check_no_warning))
    af("match_descriptors per-point depth_range", "(N,) arrays",
       MD.format(", depth_range=(np.ones(len(P1)), 100 * np.ones(len(P1)))"), "result")
    af("knn_descriptors valid", "", "ep.knn_descriptors(D1, D2, P1, P2, geom(), k=3).indices", "result")
    af("knn_descriptors k=0", "", "ep.knn_descriptors(D1, D2, P1, P2, geom(), k=0)", err=("k",))
    af("knn_descriptors constraint none", "", "ep.knn_descriptors(D1, D2, P1, P2, geom(), constraint='none')",
       err=("constraint|none",))
    af("radius_descriptors max_distance=-1", "", "ep.radius_descriptors(D1, D2, P1, P2, geom(), max_distance=-1)",
       err=("max_distance|maxDistance",))
    af("radius_descriptors without max_distance", "", "ep.radius_descriptors(D1, D2, P1, P2, geom())",
       err=("max_distance",))
    af("guided_matches valid", "", "ep.guided_matches(D1, D2, P1, P2, geom()).accept()", "result")
    FP = "ep.filter_pairs({}, P1, P2, geom(){})"
    af("filter_pairs valid", "", FP.format("[[0, 0], [1, 1]]", ""), "result")
    for pairs, extra, err, exp in [("[[0.5, 1.0]]", "", ("pairs", "integer"), "error"),
                                   ("[[0, 1, 2]]", "", ("pairs", r"\(K, 2\)"), "error"),
                                   ("[[-1, 0]]", "", ("index|range",), "error"),
                                   ("[[10**6, 0]]", "", ("index|range", "points1"), "error"),
                                   ("[(0, 0), (1, 1)]", "", (), "result"), ("[]", "", (), "result"),
                                   ("[[0, 0]]", ", constraint='bogus'", ("constraint",), "error"),
                                   ("'0 0'", "", ("pairs",), "error")]:
        af(f"filter_pairs pairs={pairs}{extra}", "", FP.format(pairs, extra), exp, err)
    af("filter_pairs points1 NaN", "", "ep.filter_pairs([[0, 0]], np.full((2, 2), np.nan), P2, geom())",
       err=("points1", "finite"))
    af("explain_pairs valid", "", "ep.explain_pairs([[0, 0]], P1, P2, geom())", "result")
    af("explain_pairs out of range", "", "ep.explain_pairs([[0, 10**6]], P1, P2, geom())", err=("index|range", "points2"))
    af("CandidateIndex valid", "", "ep.CandidateIndex(geom(), P1, P2, tol=2).pairs()", "result")
    af("CandidateIndex tol=-1", "", "ep.CandidateIndex(geom(), P1, P2, tol=-1)", err=("tol",))
    af("CandidateIndex bucket_size=0", "", "ep.CandidateIndex(geom(), P1, P2, bucket_size=0)", err=("bucket_size",))
    af("CandidateIndex points NaN", "", "ep.CandidateIndex(geom(), np.full((3, 2), np.nan), P2)", err=("points1", "finite"))
    U = "ep.undistort_points({}, K, {})"
    af("undistort_points valid", "", U.format("P1", "[0.1, 0, 0, 0]"), "result")
    af("undistort_points empty", "", U.format("[]", "[0.1, 0, 0, 0]"), "result")
    af("undistort_points dist length 3", "", U.format("P1", "[0.1, 0, 0]"), err=("dist", "4, 5"))
    af("undistort_points dist NaN", "", U.format("P1", "[np.nan, 0, 0, 0]"), err=("dist", "finite"))
    af("undistort_points K bad", "", "ep.undistort_points(P1, np.eye(2), [0.1, 0, 0, 0])", err=("K",))
    af("undistort_points points NaN", "", U.format("[[np.nan, 1]]", "[0.1, 0, 0, 0]"), err=("points", "finite"))
    af("undistort_points k1=-5", "issue: not invertible over the image; must refuse or map back",
       "import cv2\nu = ep.undistort_points(P1, K, [-5.0, 0, 0, 0])\n"
       "n = (u - K[:2, 2]) / 100.0\n"
       "back = cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3), np.zeros(3), K, "
       "np.array([-5.0, 0, 0, 0]))[0].reshape(-1, 2)\n"
       "return int((np.linalg.norm(back - P1, axis=1) > 1).sum())", "either", ("dist|k1", "invert|monoton"),
       check=check_api(lambda v: None if v == 0 else f"{v} of 60 points do not map back"))
    LC = "ep.load_calibration({})"
    af("load_calibration None", "", LC.format("None"), err=("path|None",))
    af("load_calibration 123", "", LC.format("123"), err=("path|int",))
    af("load_calibration folder", "", LC.format("'cdir'"), err=("cdir", "folder|directory"), setup=mkdir("cdir"),
       cats=("value", "type", "os"))
    af("load_calibration missing", "", LC.format("'nope.json'"), err=("nope.json", "not found"),
       cats=("value", "type", "os"))
    af("load_calibration one size", "image_size1 only", LC.format("'calib.json', image_size1=(320, 240)"),
       err=("image_size1", "image_size2|together"), setup=PAIR)
    af("load_calibration size bad", "", LC.format("'calib.json', image_size1=(0, 1), image_size2=(320, 240)"),
       err=("image_size1", "positive"), setup=PAIR)
    af("load_calibration valid", "", LC.format("'calib.json'") + ".geometry", "result", setup=PAIR)
    af("keypoints_to_array mixed", "", "import cv2\nreturn ep.keypoints_to_array([cv2.KeyPoint(1, 2, 3), 'x'])",
       err=("keypoints",))
    af("keypoints_to_array valid", "", "import cv2\nreturn ep.keypoints_to_array([cv2.KeyPoint(1, 2, 3)])", "result")
    CM = "colmap = _imp(P['colmap'])\n"
    af("load_poses missing", "", CM + "return colmap.load_poses('nope.json')", err=("nope.json",),
       cats=("value", "type", "os"))
    af("load_poses None", "", CM + "return colmap.load_poses(None)", err=("poses|path|None",))
    af("load_poses valid", "", CM + "return colmap.load_poses('poses.json')", "result", setup=COLL)
    af("load_model missing", "", CM + "return colmap.load_model('nope')", err=("nope", "does not exist"))
    af("load_model valid", "", CM + "return colmap.load_model('model')[0]", "result", setup=COLL)
    MM = CM + "return colmap.match_model('model', 'images', 'db.db'{})"
    for val, err in [(", workers=0", ("workers", "positive")), (", workers=True", ("workers",)),
                     (", tol='a'", ("tol",)), (", detector='x'", ("detector",)), (", constraint='none'", ("constraint",)),
                     (", pairs=[('a', 'b')]", ("unknown image", "'a'")), (", neighbors=0", ("neighbors",)),
                     (", depth_range=(5, 1)", ("depth_range",)), (", depth_range='foo'", ("depth_range",)),
                     (", max_features=0", ("max_features",)), (", ratio=2", ("ratio",)),
                     (", max_features=10**30", ("max_features",))]:
        af(f"match_model{val}", "bad option", MM.format(val), err=err, setup=COLL, mutable=DB_MUT)
    af("match_model cache_dir onto a file", "", MM.format(", cache_dir='cf'"),
       err=("cache|cf", NOT_FE + r".*(is a file|not a folder|not a directory)"),
       setup=S(COLL, write("cf", "x")), mutable=DB_MUT)
    af("match_model valid", "neighbors=1", MM.format(", neighbors=1") + ".n_pairs", "result", setup=COLL,
       mutable=DB_MUT)
    af("draw_matches image None", "", "ep.draw_matches(None, None, P1, P2, [[0, 0]])", err=("image1",))
    af("draw_segment_figure NaN points", "", "img = np.zeros((120, 160), np.uint8)\n"
                                             "return ep.draw_segment_figure(img, img, [[np.nan, 1]], geom().segments(P1[:1]))",
       err=("points1|points", "finite"))
    af("save_image .xyz", "", "ep.save_image('f.xyz', np.zeros((4, 4), np.uint8))", err=("f.xyz", "extension|.png"),
       cats=("value", "type", "os"))
    af("save_image parent is a file", "", "open('x', 'w').close()\nreturn ep.save_image('x/f.png', np.zeros((4, 4), np.uint8))",
       err=("x/f.png|x", "not a folder|not a directory|is a file"), cats=("value", "type", "os"))
    SC = "scenes = _imp(P['scenes'])\n"
    af("make_pair unknown", "", SC + "return scenes.make_pair('nope')", err=("nope",))
    af("make_pair image_size 0", "", SC + "return scenes.make_pair('forward', image_size=(0, 0))", err=("image_size",))
    af("make_collection 1 view", "", SC + "return scenes.make_collection(1, (64, 48))", err=("n_views|views", "2"))
    af("load_default_pair", "", "ep.datasets.load_default_pair().geometry", "result")
    return out


def g_resources() -> list[Case]:
    G = "resources"

    code = ("import time, contextlib, io\n"
            "main = _imp(P['cli'] + ':main')\n"
            "times = []\n"
            "for n in (2000, 16000):\n"
            "    t0 = time.perf_counter()\n"
            "    rc = main(['segments', 'img1.png', 'img2.png', '--calib', 'calib.json', '--random', str(n), "
            "'--out', 'f.png', '-q'])\n"
            "    times.append(time.perf_counter() - t0)\n"
            "return times")

    def quad(v):
        t1, t2 = v
        return None if t2 < 2 * 8 * max(t1, 0.05) else f"unbounded: segments --random: 2000 points {t1:.2f} s, 16000 points " \
                                                       f"{t2:.2f} s (x{t2 / t1:.0f} for x8 points: quadratic)"

    def images_written(ctx, p):
        n = len(list((ctx.d / "syn").rglob("*.png")))
        return None if n > 0 else "no view written to disk after 25 s: every view is kept in memory until the end"

    out = [
        Case("segments --random scaling", G, "issue: quadratic (a per-row recomputation)",
             [Run(code=code, expect="result", check=check_api(quad), timeout=300)], setup=PAIR, exclusive=True),
        Case("synthetic --views 100000", G, "issue: every view kept in memory (SIGINT after 25 s; RLIMIT_AS 3 GB)",
             [Run(argv=["synthetic", "syn", "--views", "100000", "--size", "320", "240"], expect="either",
                  err=("--views",), mem_gb=3.0, signal=(signal.SIGINT, ("time", 25.0), True), probe=images_written,
                  timeout=120, resource_case=True)], exclusive=True),
        C("synthetic --size 100000 100000", G, "issue: a traceback (RLIMIT_AS 2 GB)",
          ["synthetic", "syn", "--views", "2", "--size", "100000", "100000"], None, err=("--size",), mem_gb=2.0,
          timeout=90, resource_case=True, leftovers=("syn",)),
        C("segments --random 10^7", G, "a huge point count (RLIMIT_AS 2 GB)",
          ["segments", "img1.png", "img2.png", "--calib", "calib.json", "--random", "10000000", "--out", "f.png"], PAIR,
          expect="either", err=("--random",), mem_gb=2.0, timeout=120, resource_case=True),
    ]
    return out


def g_newcomer() -> list[Case]:
    G = "newcomer"
    repo = _repo()

    def git_clone(d, fix):
        if repo is None:
            raise RuntimeError("no repository found on PYTHONPATH (set EPISEG_REPO)")
        subprocess.run(["git", "init", "-q"], cwd=d, check=True)
        shutil.copy2(repo / ".gitignore", d / ".gitignore")
        subprocess.run(["git", "add", ".gitignore"], cwd=d, check=True)
        subprocess.run(["git", "-c", "user.name=x", "-c", "user.email=x@x", "commit", "-qm", "x"], cwd=d, check=True)

    def untracked(ctx):
        r = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=ctx.d, capture_output=True,
                           text=True)
        left = [ln[3:] for ln in r.stdout.splitlines()]
        return [("leftover", "files in the clone that git does not ignore: " + ", ".join(left[:5]))] if left else []

    def bench_copy(d, fix):
        shutil.copytree(repo / "benchmarks", d / "benchmarks", ignore=shutil.ignore_patterns("__pycache__"))

    SEG = ["segments", "img1.png", "img2.png", "--calib", "calib.json", "--points", "160,120", "--out", "fig.png"]
    return [
        Case("demo in a clone", G, "issue: leaves episeg_demo/ in the clone, not git-ignored",
             [Run(argv=["demo"], expect="result", timeout=300)], setup=git_clone, post=untracked, exclusive=True),
        C("demo --out", G, "writes the three files", ["demo", "--out", "o"], None, expect="result",
          check=check_files("o/matches.png", "o/segments.png", "o/matches.json"), timeout=300, exclusive=True),
        Case("bench --quick", G, "issue: overwrites the committed results (README's headline figure)",
             [Run(argv=["bench", "--quick", "--only", "compare.py", "--dir", "benchmarks", "-q"], expect="result",
                  timeout=600)], setup=bench_copy, exclusive=True,
             mutable=("benchmarks/results/quick/*", "benchmarks/__pycache__/*")),
        C("-q before the subcommand", G, "issue: -q only works after the subcommand", ["-q"] + SEG, PAIR,
          expect="result", check=all_of(FIG, check_stdout(r"\S", absent=True))),
        C("-v before the subcommand", G, "issue: -v only works after the subcommand", ["-v"] + SEG, PAIR,
          expect="result", check=FIG),
        C("--quiet before the subcommand", G, "long form", ["--quiet"] + SEG, PAIR, expect="result", check=FIG),
        C("-q after the subcommand", G, "works today", SEG + ["-q"], PAIR, expect="result",
          check=all_of(FIG, check_stdout(r"\S", absent=True))),
    ]


def _repo() -> Path | None:
    if os.environ.get("EPISEG_REPO"):
        return Path(os.environ["EPISEG_REPO"])
    for p in [str(HERE.parent), *os.environ.get("PYTHONPATH", "").split(os.pathsep)]:
        if p and (Path(p) / "episeg_cv").is_dir() and (Path(p) / ".gitignore").is_file():
            return Path(p)
    return None


def build() -> list[Case]:
    return (g_cli_flags() + g_cli_files() + g_calib_json() + g_calib_cv() + g_matches_file() + g_pairs() + g_poses()
            + g_colmap_model() + g_colmap_state() + g_feature_cache() + g_signals() + g_api_geometry()
            + g_api_matcher() + g_api_functions() + g_resources() + g_newcomer())


if __name__ == "__main__":
    sys.exit(main())
