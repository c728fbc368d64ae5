"""Hostile cases for the fuzz harness (``tests/fuzz.py``): what a generator of file contents never makes.

Each case (``HostileCase``, drawn from a fixed seed by ``draw_hostile``) comes from one generator:

- ``filekind``: a file a command reads replaced by a FIFO, a folder, a socket, a link to ``/dev/zero`` or
  ``/dev/null``, a link loop or a broken link;
- ``size``: a sparse file larger than any reader takes, an image whose header claims 100000 x 100000 px, a JPEG cut
  and closed again, a PNG with a damaged chunk, a CSV field of 100009 numbers;
- ``nesting``: JSON nested 100000 deep, TOML nested 2000 deep;
- ``values``: a duplicate JSON key, an aliased id (``"0"`` and ``"00"``), a number 1e400 in JSON, CSV or TOML;
- ``outputs``: a writing command's ``--out`` on a file or folder that exists (its own inputs, other commands'
  outputs, a folder of the user's files named like its outputs, a FIFO, a link, a lock file that is a link, a name
  longer than the system takes);
- ``physics``: workcell settings the physics cannot take (time step, sizes, near >= far, ...).

The verdict is the harness's (``fuzz.Fuzzer._judge``): a refusal is one stderr line, no traceback, no hang, no
file that existed changed; a hostile input a command surely reads (``dataset check`` reads every file of a dataset)
is never accepted; and every case ends within ``fuzz_hostile.LIMIT_S`` seconds.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import re
import shutil
import stat
import struct
import zlib
from pathlib import Path

import fuzz

#: Seconds a case may take (a refusal is expected at once).
LIMIT_S = 10.0

# -- commands that write ----------------------------------------------------------------------------------------

SMALL = fuzz.SMALL
#: Writing commands: name -> (argv with ``{t}`` the output path, whether its output is a file (suffixes) or a folder,
#: the corpus folders that are its own resumable kind, which it may complete or replace).
WRITERS = {
    "compare": (("compare", "run2", "run", "--out", "{t}"), (".json",), ()),
    "calibrate": (("calibrate", "--out", "{t}", "--poses", "3"), (".json",), ()),
    "show": (("dataset", "show", "ds", "--split", "train_pbr", "--scene", "0", "--im", "0", "--out", "{t}"),
             (".png", ".jpg"), ()),
    "objects-show": (("objects", "show", "objs", "--out", "{t}"), (".png",), ()),
    "scene": (("scene", "--out", "{t}", "--resolution", "64x48", "--blocks", "1"), (), ()),
    "datagen": (("datagen", "--out", "{t}", "--scenes", "1", "--views", "1", "--resolution", "64x48", "--blocks", "1",
                 *SMALL), (), ("ds",)),
    "train": (("train", "seg", "--data", "ds", "--out", "{t}", "--config", "cfg/train.toml", "--steps", "1",
               "--no-progress"), (), ("trun", "wts")),
    "eval": (("eval", "--data", "ds", "--weights", "wts", "--out", "{t}", "--config", "cfg/eval.toml", "--max-images",
              "1", "--threads", "1", "--no-progress"), (), ()),
    "trials": (("trials", "--episodes", "1", "--seed", "0", "--perception", "oracle", "--out", "{t}", *SMALL), (),
               ("run", "run2")),
    "export": (("trials", "--episodes", "1", "--seed", "0", "--perception", "oracle", "--out", "out/tr",
                "--export-captures", "{t}", *SMALL), (), ()),
    "perturb": (("perturb", "--weights", "wts", "--out", "{t}", "--rel-sigma", "0.01"), (), ()),
    "import": (("objects", "import", "objs/models/obj_000001.ply", "--out", "{t}", "--unit", "mm", "--no-progress"),
               (), ("objs",)),
    "merge": (("dataset", "merge", "{t}", "ds:train_pbr"), (), ()),
}
#: A folder of the user's own files, each named like a file some command writes.
FOREIGN = {"metrics.json": '{"mine": 1}\n', "rgb.png": "my picture\n", "scene.json": '{"seed": "mine"}\n',
           "campaign.json": '{"mine": true}\n', "episodes.jsonl": "my notes\n", "seg_metrics.csv": "a,b\n1,2\n",
           "my_notes-1.csv": "x\n", "objectset.json": "{}\n", "captures.json": "[]\n"}


@dataclasses.dataclass(frozen=True)
class HostileCase:
    """Case ``number`` of ``generator``: ``variant`` applied to ``rel`` (a corpus path; for ``outputs`` the output
    path) and ``command`` run (a ``fuzz.COMMANDS`` name, or a ``WRITERS`` name for ``outputs``)."""

    number: int
    generator: str
    variant: str
    rel: str
    command: str

    @property
    def kind(self) -> str:  # what ``fuzz.Fuzzer._judge`` reads
        return fuzz.file_kind(self.rel) or "output"


GENERATORS = ("filekind", "size", "nesting", "values", "outputs", "physics")
FILE_VARIANTS = ("fifo", "folder", "socket", "devzero", "devnull", "loop", "broken")


def _variants(generator: str, rel: str) -> tuple[str, ...]:
    """The variants of ``generator`` that apply to the corpus file ``rel``."""
    suffix, kind = Path(rel).suffix, fuzz.file_kind(rel)
    if generator == "filekind":
        return FILE_VARIANTS
    if generator == "size":
        out = ["sparse"]
        if suffix == ".png":
            out += ["header-bomb", "png-crc"]
        if suffix == ".jpg":
            out += ["jpeg-cut", "header-bomb"]
        if kind == "results_csv":
            out += ["csv-field"]
        return tuple(out)
    if generator == "nesting":
        return ("deep",) if suffix in (".json", ".toml", ".jsonl") else ()
    if generator == "values":
        out = []
        if suffix == ".json":
            out += ["dupkey", "1e400"]
            if kind in ("bop_json", "models_info"):
                out.append("alias")
        if suffix in (".csv", ".toml", ".jsonl"):
            out.append("1e400")
        return tuple(out)
    return ()


def draw_hostile(base: Path, n: int, seed: int = 0, start: int = 0) -> list[HostileCase]:
    """``n`` cases from ``seed`` (numbered from ``start``), the generators in turn: the file generators on a
    (file, light command that reads it) pair, ``outputs`` on a writer and a target, ``physics`` on a setting."""
    files = fuzz.corpus_files(base)
    pairs = sorted((k, c.name) for c in fuzz.COMMANDS for k in c.kinds if k in files and not c.heavy)
    heavy = sorted((k, c.name) for c in fuzz.COMMANDS for k in c.kinds if k in files and c.heavy)
    rng = random.Random(f"hostile:{seed}")
    cases: list[HostileCase] = []
    while len(cases) < n:
        i = start + len(cases)
        gen = GENERATORS[len(cases) % len(GENERATORS)]
        if gen == "outputs":
            writer = rng.choice(sorted(WRITERS))
            cases.append(HostileCase(i, gen, *_output_target(rng, base, writer), writer))
            continue
        if gen == "physics":
            cases.append(HostileCase(i, gen, rng.choice(PHYSICS), "cfg/datagen.toml" if rng.random() < 0.3
                                     else "cfg/phys.toml", "scene"))
            continue
        kind, cmd = rng.choice(pairs if rng.random() < 0.9 else heavy)
        rel = rng.choice([f for f in files[kind] if fuzz.reads(fuzz.BY_NAME[cmd], f)] or files[kind])
        options = _variants(gen, rel)
        if options:
            cases.append(HostileCase(i, gen, rng.choice(options), rel, cmd))
    return cases


def _output_target(rng: random.Random, base: Path, writer: str) -> tuple[str, str]:
    """(variant, output path) for ``writer``: an existing corpus file or folder (not its own kind), a folder of the
    user's files, a FIFO, a link, a lock file that is a link, or too long a name."""
    _, suffixes, own = WRITERS[writer]
    variant = rng.choice(["existing", "existing", "existing", "foreign", "fifo", "link", "lock-link", "long"])
    if variant == "lock-link" and suffixes:  # a file's writer takes no lock
        variant = "link"
    if variant == "existing":
        if suffixes:
            pool = [p for p in base.rglob("*") if p.is_file() and p.suffix in suffixes]
        else:
            pool = [p for p in base.rglob("*") if p.is_dir()]
        pool = [p.relative_to(base).as_posix() for p in pool]
        pool = [p for p in pool if not any(p == o or p.startswith(o + "/") for o in own)]
        return variant, rng.choice(sorted(pool))
    name = "out/x" + (suffixes[0] if suffixes else "")
    if variant == "long":
        return variant, ("out/" + "n" * 300 + (suffixes[0] if suffixes else "")) if rng.random() < 0.5 \
            else "out/" + "d/" * 2100 + "x" + (suffixes[0] if suffixes else "")
    return variant, "out/foreign" if variant in ("foreign", "lock-link") and not suffixes else name


# -- applying a case --------------------------------------------------------------------------------------------

def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _size_variant(variant: str, data: bytes, target: Path) -> bytes | None:
    """New bytes of ``target`` for a ``size`` variant (None: the file was made in place)."""
    if variant == "sparse":
        target.write_bytes(b"")
        os.truncate(target, 9 << 30)  # 9 GiB, no block of it written
        return None
    if variant == "header-bomb":
        if data[:8] == b"\x89PNG\r\n\x1a\n":
            ihdr = struct.pack(">II", 100000, 100000) + data[24:29]
            return data[:8] + _png_chunk(b"IHDR", ihdr) + data[33:]
        i = data.find(b"\xff\xc0")
        i = i if i >= 0 else data.find(b"\xff\xc2")
        return data[:i + 5] + struct.pack(">HH", 50000, 50000) + data[i + 9:]
    if variant == "png-crc":
        mid = len(data) // 2
        return data[:mid] + bytes(b ^ 0x55 for b in data[mid:mid + 8]) + data[mid + 8:]
    if variant == "jpeg-cut":
        return data[:len(data) // 2] + b"\xff\xd9"
    lines = data.decode().splitlines()  # csv-field
    row = lines[1].split(",")
    row[4] = " ".join(["1"] * 100009)
    return ("\n".join([lines[0], ",".join(row), *lines[2:]]) + "\n").encode()


def _values_variant(variant: str, data: bytes, rel: str, rng: random.Random) -> bytes:
    text = data.decode()
    if variant == "dupkey":
        doc = json.loads(text)
        if isinstance(doc, dict) and doc:
            k = rng.choice(sorted(doc))
            return ("{" + json.dumps(k) + ": " + json.dumps(doc[k]) + ", " + text.lstrip()[1:]).encode()
        return ('{"a": 1, "a": 2}').encode()
    if variant == "alias":
        doc = json.loads(text)
        k = sorted(doc)[0]
        return ("{" + json.dumps("0" + k) + ": " + json.dumps(doc[k]) + ", " + text.lstrip()[1:]).encode()
    numbers = [m for m in re.finditer(r"(?<![\w.\"])-?\d+\.\d+(?:[eE][-+]?\d+)?(?![\w\"])", text)]
    if not numbers:
        return text.encode() + b"\n1e400\n"
    m = rng.choice(numbers)
    return (text[:m.start()] + "1e400" + text[m.end():]).encode()


def apply(case: HostileCase, d: Path) -> tuple[str, bool]:
    """Make ``case``'s hostile input in the corpus copy ``d``: (what was done, whether the command surely must
    refuse it)."""
    target = d / case.rel
    rng = random.Random(f"hostile-apply:{case.number}")
    sure = case.command == "check"  # reads every file of the dataset
    if case.generator == "outputs":
        return _apply_output(case, d), False
    if case.generator == "physics":
        return _apply_physics(case, d), case.variant == "near>far"
    data = target.read_bytes()
    target.unlink()
    if case.generator == "filekind":
        _make_kind(case.variant, target)
        return f"{case.rel} -> {case.variant}", sure
    if case.generator == "size":
        new = _size_variant(case.variant, data, target)
        sure = sure or (case.variant == "csv-field" and case.command == "trials-csv")
    elif case.generator == "nesting":
        new = (b"a = " + b"[" * 2000 + b"]" * 2000 + b"\n") if case.rel.endswith(".toml") else \
            b"[" * 100000 + b"]" * 100000 + (b"\n" if case.rel.endswith(".jsonl") else b"")
    else:
        new = _values_variant(case.variant, data, case.rel, rng)
        sure = sure and case.variant != "1e400" or case.variant == "1e400" and case.command == "trials-csv"
    if new is not None:
        target.write_bytes(new)
    return f"{case.rel} -> {case.variant}", sure


def _make_kind(variant: str, target: Path) -> None:
    if variant == "fifo":
        os.mkfifo(target)
    elif variant == "folder":
        target.mkdir()
        (target / "x").write_text("x")
    elif variant == "socket":
        os.mknod(target, 0o600 | stat.S_IFSOCK)
    elif variant in ("devzero", "devnull"):
        target.symlink_to(f"/dev/{variant[3:]}")
    elif variant == "loop":
        target.symlink_to(target.name)
    else:
        target.symlink_to(target.name + ".gone")


def _apply_output(case: HostileCase, d: Path) -> str:
    (d / "out").mkdir(exist_ok=True)
    t = d / case.rel
    if case.variant == "foreign" and WRITERS[case.command][1]:
        t.write_text('{"mine": 1}\n')
    elif case.variant == "foreign":
        t.mkdir(parents=True, exist_ok=True)
        for name, text in FOREIGN.items():
            (t / name).write_text(text)
    elif case.variant == "fifo":
        os.mkfifo(t)
    elif case.variant == "link":
        t.symlink_to(d / "ds" / "camera.json")
    elif case.variant == "lock-link":
        t.mkdir(parents=True, exist_ok=True)
        (t / ".posegrasp.lock").symlink_to(d / "ds" / "camera.json")
    return f"--out {case.rel[:60]} ({case.variant})"


def out_argv(case: HostileCase) -> list[str]:
    """The argv of an ``outputs`` case."""
    return [a.replace("{t}", case.rel) for a in WRITERS[case.command][0]]


#: Settings the physics cannot take: (variant, TOML text of a workcell).
PHYSICS = ("timestep=0", "timestep=1e-300", "timestep=5", "timestep=-0.002", "table=1e308", "table=0",
           "near>far", "near=far", "pick=0", "pick=1e3", "look=0", "look=-1", "camera=1e9", "fovy=0", "fovy=180",
           "qpos=1e308", "width=0", "overview=same")
_PHYSICS_TOML = {
    "timestep=0": "timestep = 0.0", "timestep=1e-300": "timestep = 1e-300", "timestep=5": "timestep = 5.0",
    "timestep=-0.002": "timestep = -0.002", "table=1e308": "table_half_size = [1e308, 0.75, 0.02]",
    "table=0": "table_half_size = [0.0, 0.0, 0.0]", "near>far": "[hand_camera]\nnear = 3.0\nfar = 1.0",
    "near=far": "[hand_camera]\nnear = 1.0\nfar = 1.0", "pick=0": "[pick_area]\nhalf_size = [0.0, 0.0]",
    "pick=1e3": "[pick_area]\nhalf_size = [1000.0, 1000.0]", "look=0": "look_height = 0.0",
    "look=-1": "look_height = -1.0", "camera=1e9": "[hand_camera]\nmount_pos = [1e9, 0.0, 0.0]",
    "fovy=0": "[hand_camera]\nfovy_deg = 0.0", "fovy=180": "[hand_camera]\nfovy_deg = 180.0",
    "qpos=1e308": "home_qpos = [1e308, 3.34, 5.10, 2.65, 1.64, 2.28]", "width=0": "[hand_camera]\nwidth = 0",
    "overview=same": "overview_pos = [0.25, 0.1, 0.2]\noverview_target = [0.25, 0.1, 0.2]",
}


def _apply_physics(case: HostileCase, d: Path) -> str:
    text = _PHYSICS_TOML[case.variant]
    if case.rel == "cfg/datagen.toml":  # the same under a datagen file's [workcell] table
        text = "\n".join(("[workcell." + ln[1:] if ln.startswith("[") else ln) for ln in text.splitlines())
        text = text if text.startswith("[") else "[workcell]\n" + text
    (d / case.rel).unlink(missing_ok=True)
    (d / case.rel).write_text(text + "\n")
    return f"{case.rel}: {case.variant}"


def physics_argv(case: HostileCase) -> list[str]:
    if case.rel == "cfg/datagen.toml":
        return ["datagen", "--out", "out/d", "--config", case.rel, "--scenes", "1", "--views", "1",
                "--resolution", "64x48", "--blocks", "1", *SMALL]
    return ["scene", "--out", "out/s", "--config", case.rel, "--resolution", "64x48", "--blocks", "1"]


def run_hostile(fuzzer: "fuzz.Fuzzer", case: HostileCase, zygote: "fuzz.Zygote", keep: bool = False) -> fuzz.Verdict:
    """Run ``case`` in a fresh copy of the corpus and judge it as ``fuzz.Fuzzer`` judges a mutation."""
    d = fuzzer.work / f"hcase{case.number:05d}"
    if d.exists():
        shutil.rmtree(d)
    fuzz._link_copy(fuzzer.base, d)
    try:
        what, sure = apply(case, d)
    except Exception as e:  # the harness's own failure
        return fuzz.Verdict(case, "(not applied)", 0, 0.0, f"hostile case failed: {e!r}", "harness")
    before = fuzz.tree_hashes(d)
    if case.generator == "outputs":
        argv, cmd = out_argv(case), fuzz.Command(case.command, (), True, (), vouches=False)
    elif case.generator == "physics":
        argv, cmd = physics_argv(case), fuzz.Command("scene", (), False, (), vouches=False)
    else:
        cmd = fuzz.BY_NAME[case.command]
        fill = {"out": "out", **fuzz._show_args(case.rel)}
        argv = [a.format(**fill) for a in cmd.argv]
    o = zygote.run(argv, d, 60.0)
    m = fuzz.Mutation(what, b"", sure)
    problem, category = fuzzer._judge(case, cmd, m, o, d, before, zygote)
    if problem is None and o.rc != 0 and o.seconds > LIMIT_S:
        problem, category = f"refused after {o.seconds:.1f} s (more than {LIMIT_S:g} s)", "slow"
    if problem is None and o.rc == 0 and case.generator == "outputs" and case.variant != "existing":
        problem, category = "accepted an output path it must refuse", "false-ok"
    if problem is None or not keep:
        shutil.rmtree(d, ignore_errors=True)
    return fuzz.Verdict(case, what, o.rc, o.seconds, problem, category)
