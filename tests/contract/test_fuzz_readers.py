"""Fuzz the file readers: every input ends in a result or a one-line ValueError/TypeError.

Readers: the calibration parser (JSON, OpenCV YAML, OpenCV XML), the matches reader
(JSON, NPZ) and the poses-JSON reader. Inputs are valid files with random changes
(values replaced by any JSON value, keys dropped or added, matrices of any shape and
content, OpenCV matrices with any rows/cols/dt/data) and byte-level damage (flips,
truncation, insertion, random bytes).

As a test (bounded, a few seconds)::

    python -m pytest -q tests/contract/test_fuzz_readers.py

As a script (longer; collects the distinct failures instead of stopping at the first)::

    python tests/contract/test_fuzz_readers.py --long [--examples 3000]

A failure is any other exception type, a ValueError/TypeError whose message has more
than one line, or a crash of the process.
"""

from __future__ import annotations

import copy
import importlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

# Module paths: the only place that names modules of episeg_cv ("module:attr").
PATHS = {
    "load_calibration": "episeg_cv:load_calibration",           # top level (lives in episeg_cv.io.calibration)
    "read_matches": "episeg_cv.io:read_matches",
    "load_poses": "episeg_cv.colmap:load_poses",
}


def _imp(spec: str):
    mod, _, attr = spec.partition(":")
    obj = importlib.import_module(mod)
    for a in filter(None, attr.split(".")):
        obj = getattr(obj, a)
    return obj


#: The suite's bound, applied to these tests only (a profile loaded here would change every hypothesis
#: test of the session).
SUITE = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                 suppress_health_check=list(HealthCheck))

#: In --long mode failures are collected here (signature -> example) instead of raised.
COLLECT: dict | None = None


# --------------------------------------------------------------------------------------
# The property
# --------------------------------------------------------------------------------------
def outcome(reader: str, suffix: str, content: bytes, **kw) -> str | None:
    """Run ``reader`` on ``content`` saved with ``suffix``; None if fine, else a failure signature."""
    fn = _imp(PATHS[reader])
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"input{suffix}"
        p.write_bytes(content)
        try:
            fn(p, **kw)
        except (ValueError, TypeError) as e:
            msg = str(e).strip()
            if "\n" in msg:
                return f"{reader}{suffix}: {type(e).__name__} with a {len(msg.splitlines())}-line message: " \
                       f"{msg.splitlines()[0][:80]!r}..."
            if not msg:
                return f"{reader}{suffix}: {type(e).__name__} with an empty message"
            return None
        except RecursionError as e:
            return f"{reader}{suffix}: RecursionError: {str(e)[:60]}"
        except Exception as e:  # noqa: BLE001 - any other type is the failure we look for
            return f"{reader}{suffix}: {type(e).__module__}.{type(e).__name__}: {str(e).splitlines()[0][:100] if str(e) else ''}"
    return None


def check(reader: str, suffix: str, content: bytes, **kw):
    why = outcome(reader, suffix, content, **kw)
    if why is None:
        return
    if COLLECT is not None:
        key = why.split(": ", 2)[:2]
        COLLECT.setdefault(" | ".join(key), (why, content[:300]))
        return
    raise AssertionError(why)


# --------------------------------------------------------------------------------------
# Valid inputs
# --------------------------------------------------------------------------------------
K = [[250.0, 0.0, 159.5], [0.0, 250.0, 119.5], [0.0, 0.0, 1.0]]
R = [[0.9995465663233841, -0.029959933975254073, -0.0030106655959987894],
     [0.029955157425132516, 0.9995499319002199, -0.0016193152567822947],
     [0.0030578251696332438, 0.0015283960428292382, 0.9999941568383128]]
T = [-0.2224, -0.0435, -1.0068]
CALIB = {"K1": K, "K2": K, "R": R, "t": T, "image_size1": [320, 240], "image_size2": [320, 240],
         "dist1": [0.01, 0.0, 0.0, 0.0], "dist2": [0.0, 0.0, 0.0, 0.0, 0.0]}
CALIB_KEYS = ["K1", "K2", "R", "t", "image_size1", "image_size2", "dist1", "dist2", "K", "image_size", "cameras",
              "P1", "P2", "M1", "M2", "D1", "D2", "T", "R1", "R2", "t1", "t2", "width", "height"]
MATCHES = {"meta": {"format": "episeg-matches", "format_version": 1, "command": "match",
                    "settings": {"tol": 2.0}, "counts": {"matches": 2}},
           "keypoints1": [[10.0, 20.0], [30.5, 40.25], [50.0, 60.0]],
           "keypoints2": [[11.0, 21.0], [31.5, 41.25]],
           "matches": [[0, 0], [1, 1]], "distances": [0.1, 0.2], "labels": ["on_segment", "off_line"]}
POSES = {"images": [{"name": f"view_{i:03d}.png", "width": 160, "height": 120,
                     "K": [[125.0, 0.0, 79.5], [0.0, 125.0, 59.5], [0.0, 0.0, 1.0]],
                     "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "t": [-0.5 * i, 0.0, 0.0]}
                    for i in range(2)]}
POSE_KEYS = ["name", "width", "height", "K", "R", "t", "dist", "depth_range"]


def cv_yaml(entries: dict) -> str:
    out = ["%YAML:1.0", "---"]
    for k, v in entries.items():
        if isinstance(v, tuple):
            rows, cols, dt, data = v
            out += [f"{k}: !!opencv-matrix", f"   rows: {rows}", f"   cols: {cols}", f"   dt: {dt}",
                    "   data: [ " + ", ".join(data) + " ]"]
        else:
            out.append(f"{k}: {v}")
    return "\n".join(out) + "\n"


def cv_xml(entries: dict) -> str:
    out = ['<?xml version="1.0"?>', "<opencv_storage>"]
    for k, v in entries.items():
        if isinstance(v, tuple):
            rows, cols, dt, data = v
            out.append(f'<{k} type_id="opencv-matrix"><rows>{rows}</rows><cols>{cols}</cols><dt>{dt}</dt>'
                       f"<data>{' '.join(data)}</data></{k}>")
        else:
            out.append(f"<{k}>{v}</{k}>")
    return "\n".join(out + ["</opencv_storage>"]) + "\n"


def _flat(m):
    return [repr(float(x)) for row in m for x in row]


CV_ENTRIES = {"M1": (3, 3, "d", _flat(K)), "D1": (1, 5, "d", ["0."] * 5), "M2": (3, 3, "d", _flat(K)),
              "D2": (1, 5, "d", ["0."] * 5), "R": (3, 3, "d", _flat(R)), "T": (3, 1, "d", [repr(x) for x in T]),
              "image_width": "320", "image_height": "240"}


# --------------------------------------------------------------------------------------
# Strategies
# --------------------------------------------------------------------------------------
leaf = st.one_of(st.none(), st.booleans(), st.integers(-2 ** 70, 2 ** 70), st.floats(allow_nan=True, allow_infinity=True),
                 st.sampled_from([0, 1, -1, 1e-300, 1e300, 320, 240, 3]), st.text(max_size=6))
json_value = st.recursive(leaf, lambda ch: st.lists(ch, max_size=4) | st.dictionaries(st.text(max_size=5), ch, max_size=3),
                          max_leaves=10)
number = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10 ** 6, 10 ** 6),
                   st.sampled_from([0.0, 1.0, -1.0, 1e308, -1e308, 5e-324]))
matrix = st.one_of(st.lists(st.lists(number, max_size=4), max_size=4), st.lists(number, max_size=10),
                   st.lists(st.lists(st.one_of(number, leaf), max_size=4), max_size=4))
any_value = st.one_of(json_value, matrix)


@st.composite
def mutated_dict(draw, base: dict, keys: list, path=()):
    d = copy.deepcopy(base)
    target = d
    for k in path:
        target = target[k]
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["set", "set", "drop", "add"]))
        k = draw(st.sampled_from(keys))
        if op == "set":
            target[k] = draw(any_value)
        elif op == "drop":
            target.pop(k, None)
        else:
            target[draw(st.text(max_size=6))] = draw(json_value)
    return d


@st.composite
def damaged(draw, data: bytes):
    """Byte-level damage: flips, truncation, insertion, or random bytes."""
    op = draw(st.sampled_from(["flip", "truncate", "insert", "random", "none"]))
    b = bytearray(data)
    if op == "flip" and b:
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(b) - 1))
            b[i] = draw(st.integers(0, 255))
    elif op == "truncate":
        b = b[:draw(st.integers(0, len(b)))]
    elif op == "insert":
        i = draw(st.integers(0, len(b)))
        b[i:i] = draw(st.binary(max_size=20))
    elif op == "random":
        b = bytearray(draw(st.binary(max_size=400)))
    return bytes(b)


def dumps(obj) -> bytes:
    return json.dumps(obj, allow_nan=True).encode()


@st.composite
def cv_entries(draw):
    e = dict(CV_ENTRIES)
    for _ in range(draw(st.integers(1, 3))):
        k = draw(st.sampled_from(list(CV_ENTRIES) + ["image_size1", "extra"]))
        kind = draw(st.sampled_from(["matrix", "scalar", "drop"]))
        if kind == "drop":
            e.pop(k, None)
        elif kind == "scalar":
            e[k] = draw(st.sampled_from(["abc", '"x"', "1e400", ".nan", "-3", "[ 1, 2 ]", "", "{ a: 1 }", "0"]))
        else:
            rows, cols = draw(st.integers(0, 5)), draw(st.integers(0, 5))
            dt = draw(st.sampled_from(["d", "f", "i", "u", "s", "c", "w", "x", "2d"]))
            data = draw(st.lists(st.one_of(number.map(lambda x: repr(float(x)) if isinstance(x, float) else str(x)),
                                           st.sampled_from([".nan", ".inf", "-.inf", "abc", "1e400", "0x10"])),
                                 max_size=12))
            e[k] = (rows, cols, dt, [d.replace("nan", ".nan").replace("inf", ".inf") if d in ("nan", "inf") else d
                                     for d in data])
    return e


def _npz(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


VALID_NPZ = _npz({"meta": np.array(json.dumps(MATCHES["meta"])), "keypoints1": np.array(MATCHES["keypoints1"]),
                  "keypoints2": np.array(MATCHES["keypoints2"]), "matches": np.array(MATCHES["matches"]),
                  "distances": np.array(MATCHES["distances"], np.float32),
                  "labels": np.array(MATCHES["labels"], dtype="U16")})
arrays = st.one_of(
    st.lists(number, max_size=6).map(lambda v: np.array(v, dtype=np.float64)),
    st.lists(st.lists(st.integers(-5, 5), min_size=2, max_size=2), max_size=4).map(lambda v: np.array(v, dtype=np.int64)),
    st.text(max_size=20).map(np.array), st.sampled_from([np.zeros((0,)), np.zeros((2, 3, 4)), np.array(b"\x00\xff"),
                                                          np.array([1 + 2j]), np.array(["a", "b"])]))


@st.composite
def npz_files(draw):
    base = {"meta": np.array(json.dumps(MATCHES["meta"])), "keypoints1": np.array(MATCHES["keypoints1"]),
            "keypoints2": np.array(MATCHES["keypoints2"]), "matches": np.array(MATCHES["matches"]),
            "distances": np.array(MATCHES["distances"], np.float32), "labels": np.array(MATCHES["labels"], dtype="U16")}
    for _ in range(draw(st.integers(1, 3))):
        k = draw(st.sampled_from(list(base) + ["extra"]))
        if draw(st.booleans()):
            base.pop(k, None)
        else:
            base[k] = draw(arrays) if k != "meta" else np.array(draw(st.text(max_size=30) | json_value.map(json.dumps)))
    return _npz(base)


# --------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------
DEEP = b'{"K1": ' + b"[" * 100000 + b"1" + b"]" * 100000 + b"}"


@SUITE
@given(st.one_of(mutated_dict(CALIB, CALIB_KEYS).map(dumps), st.just(dumps(CALIB)).flatmap(damaged),
                 json_value.map(dumps), mutated_dict({"cameras": [{"K": K, "R": R, "t": T}, {"K": K, "R": R, "t": T}]},
                                                     ["K", "R", "t", "image_size", "dist"], ("cameras", 1)).map(dumps)))
@example(b"\xef\xbb\xbf" + dumps(CALIB))
@example(b"")
def test_calibration_json(content):
    check("load_calibration", ".json", content)


@SUITE
@given(st.one_of(cv_entries().map(lambda e: cv_yaml(e).encode()), st.just(cv_yaml(CV_ENTRIES).encode()).flatmap(damaged)))
@example(b"")
def test_calibration_yaml(content):
    check("load_calibration", ".yml", content)


@SUITE
@given(st.one_of(cv_entries().map(lambda e: cv_xml(e).encode()), st.just(cv_xml(CV_ENTRIES).encode()).flatmap(damaged)))
@example(b"")
def test_calibration_xml(content):
    check("load_calibration", ".xml", content)


@SUITE
@given(st.one_of(mutated_dict(MATCHES, list(MATCHES)).map(dumps), st.just(dumps(MATCHES)).flatmap(damaged),
                 mutated_dict(MATCHES, ["format", "format_version", "counts"], ("meta",)).map(dumps),
                 json_value.map(dumps)))
@example(b"")
def test_matches_json(content):
    check("read_matches", ".json", content)


@SUITE
@given(st.one_of(npz_files(), st.just(VALID_NPZ).flatmap(damaged)))
@example(b"")
def test_matches_npz(content):
    check("read_matches", ".npz", content)


@SUITE
@given(st.one_of(mutated_dict(POSES, POSE_KEYS, ("images", 1)).map(dumps), st.just(dumps(POSES)).flatmap(damaged),
                 mutated_dict(POSES, ["images"]).map(dumps), json_value.map(dumps)))
@example(b"")
def test_poses_json(content):
    check("load_poses", ".json", content)


DEEP_INPUTS = {
    "calibration json": ("load_calibration", ".json", DEEP),
    "calibration yml": ("load_calibration", ".yml", b"%YAML:1.0\n---\nM1: " + b"[" * 100000 + b"\n"),
    "calibration xml": ("load_calibration", ".xml",
                        b'<?xml version="1.0"?>\n<opencv_storage>\n' + b"<a>" * 100000 + b"</opencv_storage>\n"),
    "matches json": ("read_matches", ".json", b"[" * 100000 + b"]" * 100000),
    "poses json": ("load_poses", ".json", b'{"images": ' + b"[" * 100000 + b"]" * 100000 + b"}"),
}


def test_deeply_nested():
    """Nesting 100000 levels deep: a one-line error, not a RecursionError (checked in a child process: a
    parser may overflow the C stack)."""
    import subprocess

    bad = []
    for name, (reader, suffix, content) in DEEP_INPUTS.items():
        code = ("import sys, test_fuzz_readers as f; why = f.outcome(sys.argv[1], sys.argv[2], sys.stdin.buffer.read()); "
                "print(why or 'ok')")
        r = subprocess.run([sys.executable, "-c", code, reader, suffix], input=content, capture_output=True,
                           cwd=Path(__file__).resolve().parent, timeout=120)
        out = r.stdout.decode().strip()
        if r.returncode != 0:
            bad.append(f"{name}: the process died (exit {r.returncode}) {r.stderr.decode()[-200:]!r}")
        elif out != "ok":
            bad.append(f"{name}: {out}")
    assert not bad, "; ".join(bad)


TESTS = [test_calibration_json, test_calibration_yaml, test_calibration_xml, test_matches_json, test_matches_npz,
         test_poses_json]


def main(argv=None) -> int:
    import argparse
    import time

    ap = argparse.ArgumentParser(description="Fuzz the readers; print the distinct failures.")
    ap.add_argument("--long", action="store_true", help="many examples per reader (default: the suite's bound)")
    ap.add_argument("--examples", type=int, default=5000, help="examples per reader with --long")
    ap.add_argument("--seed", type=int, default=None)
    args = ap.parse_args(argv)
    global COLLECT
    COLLECT = {}
    n = args.examples if args.long else 40
    t0 = time.perf_counter()
    for t in TESTS:
        s = settings(max_examples=n, deadline=None, suppress_health_check=list(HealthCheck), database=None,
                     derandomize=args.seed is None and not args.long)
        before = len(COLLECT)
        t1 = time.perf_counter()
        inner = t.hypothesis.inner_test
        given_t = settings(s)(t)
        if args.seed is not None:
            from hypothesis import seed
            given_t = seed(args.seed)(given_t)
        given_t()
        print(f"{t.__name__}: {n} examples in {time.perf_counter() - t1:.0f} s, "
              f"{len(COLLECT) - before} new distinct failure(s)", flush=True)
        del inner
    try:
        test_deeply_nested()
        print("test_deeply_nested: ok")
    except AssertionError as e:
        for part in str(e).split("; "):
            COLLECT.setdefault("deep | " + part.split(":")[0], (f"deeply nested {part}", b"(100000 levels)"))
    print(f"\n{len(COLLECT)} distinct failure signature(s) in {time.perf_counter() - t0:.0f} s:")
    for key, (why, content) in sorted(COLLECT.items()):
        print(f"- {why}\n    input (first bytes): {content[:120]!r}")
    return 1 if COLLECT else 0


if __name__ == "__main__":
    sys.exit(main())
