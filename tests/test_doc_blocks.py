"""Every shell block of the user documentation, run as written on the simulators.

The files are listed in :data:`DOCS`. Every fence in them carries its language (``sh`` a
command a user types; ``text``/``console`` output or a listing; ``toml``, ``python``,
``json``). Per file, its ``sh`` blocks run in order in ONE bash (``set -euo pipefail``; the
shell's variables and background jobs carry from block to block, each block starting at
the root of the clone) in a temporary directory laid out like a clone (``examples/`` copied,
``tests/data/`` and ``.venv`` linked: nothing is written into the checkout), with the
running interpreter's ``bin`` first on PATH, a timeout per block, and every process the
blocks started ended at the end (the bash runs in its own session; whatever is left of it
is stopped and counted as a failure of the document). A failure names the file, the
block's line, the command and the tail of its stderr.

What is not run, and why, is written here: a block marked in the document with
``<!-- doc-test: hardware (REASON) -->`` (it needs a real instrument; few), and the blocks
of :data:`COVERED` (run by another test, named with the reason). Well-known ports in the
blocks and in the copied examples (:data:`PORTS`) are replaced by free ones: the machine
may run another afmctl, or the suite's other worker.

``python`` blocks: docs/PYTHON.md's are executed in order by
tests/test_python_api.py::test_python_md_runs_and_prints_the_command_lines_figures, which
also checks their figures against the command line; the ``python`` blocks of the other
files are API sketches (``amp`` an open driver, ``...``), read, not run.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: the documents whose shell blocks are executed
DOCS = ("README.md", "docs/LEARNING.md", "docs/CONTROLLER.md", "docs/DRIVERS.md", "docs/ZENOH.md",
        "docs/SIM.md", "docs/PYTHON.md")

#: the languages a fence may carry in those documents
LANGUAGES = {"sh", "text", "console", "toml", "python", "json"}

#: blocks run by another test, keyed by (document, the start of one of the block's lines):
#: the reason beside
COVERED = {
    ("README.md", "make demo"):
        "`make test` is this suite (CI's .ci/run runs it on a fresh clone); `make demo` sets up .venv "
        "as `make test` does and runs `afmctl demo --out demo-out`, which tests/test_demo.py runs reduced "
        "(64 px, --quick, three model kinds): the full demo is a few minutes of CPU on 2 cores",
    ("docs/SIM.md", "scan_grating_rates(sc).save_npz"):
        "tests/test_image_dynamics.py::test_cli_identifies_from_images_and_bad_input_is_one_line makes the same "
        "scans (scan_grating_lines(lines_per_range=4), scan_grating_rates with its defaults) and runs "
        "`afmctl identify --model preisach+dynamics --from-images` on them; its module fixture identifies the "
        "+creep chain from such scans (benchmarks/image_dynamics.py); the block as written is 30-40 s of CPU",
}

#: most hardware-marked blocks allowed: a block that needs a real instrument is the exception
MAX_HARDWARE = 3

#: keyed as COVERED: substrings a block prints that its document states too (a figure in a comment, a reply
#: quoted in the text): checked in both, so the document and the output cannot drift apart
EXPECT = {
    ("README.md", "python examples/make_data.py data --check volts.csv"):
        ["max 0.38 %", "rms 0.19 %"],
    ("README.md", "afmctl model validate --model pea.json"):
        ["55.8", "290"],
    ("docs/ZENOH.md", "afmctl run --config examples/sim_zenoh.toml"):
        ["already running in queue mode", "the queue ran empty"],
}

#: commands shortened by their own options, keyed by (document, the command's start): the
#: options added and why. Each must match one line of the document.
SHORTEN = {
    ("README.md", "afmctl calibrate --config tour.toml"):
        (["--kind", "pi", "--dwell-s", "0.3", "--gap-s", "0.1", "--periods", "2", "--f-min-Hz", "50",
          "--sweep-V-per-s", "600"],
         "the full excitation (about a minute on the device's clock) and the `auto` selection took over "
         "4 minutes on the loaded 2-core machine; calibrate's own options shorten the excitation, the "
         "device, the recorder and the identification are the same"),
}

#: loopback ports written in the documents and examples; each is replaced by a free one
PORTS = ("50000", "7447", "7500", "8765")

#: seconds any one block may take (the README tour took 2-3.5 min at load 12-19)
TIMEOUT_S = 420.0

MARKER = re.compile(r"<!--\s*doc-test:\s*(\w+)\s*(.*?)\s*-->")


@dataclass(frozen=True)
class Block:
    doc: str
    line: int           # the line of the opening fence (1-based)
    lang: str
    text: str
    marker: str         # "hardware ..." from the comment before the fence, or ""

    def has(self, key: tuple[str, str]) -> bool:
        """``key`` = (document, the start of one of the block's lines) names this block."""
        return key[0] == self.doc and any(ln.lstrip().startswith(key[1]) for ln in self.text.splitlines())


def fences(doc: str) -> list[Block]:
    """Every fenced block of ``doc`` (a path relative to the repository root)."""
    lines = (ROOT / doc).read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    k = 0
    while k < len(lines):
        m = re.match(r"^(\s*)```(\S*)\s*$", lines[k])
        if not m:
            k += 1
            continue
        end = next((j for j in range(k + 1, len(lines)) if lines[j].strip() == "```"), None)
        assert end is not None, f"{doc}:{k + 1}: a fence that is never closed"
        before = next((lines[j] for j in range(k - 1, -1, -1) if lines[j].strip()), "")
        mark = MARKER.search(before)
        out.append(Block(doc, k + 1, m.group(2), "\n".join(lines[k + 1:end]) + "\n",
                         f"{mark.group(1)} {mark.group(2)}".strip() if mark else ""))
        k = end + 1
    return out


def shell_blocks(doc: str) -> list[Block]:
    return [b for b in fences(doc) if b.lang == "sh"]


def to_run(doc: str) -> list[Block]:
    return [b for b in shell_blocks(doc) if not b.marker.startswith("hardware") and not any(map(b.has, COVERED))]


# ---------------------------------------------------------------------------------- checks

def test_every_fence_says_what_it_holds():
    unlabelled = [f"{b.doc}:{b.line}" for doc in DOCS for b in fences(doc) if b.lang not in LANGUAGES]
    assert not unlabelled, f"fences without a language of {sorted(LANGUAGES)}: {unlabelled}"


def test_every_shell_block_is_run_or_says_why_not():
    """A new ``sh`` block is run by :func:`test_the_documents_shell_blocks_run_as_written`
    unless it is hardware-marked (with a reason) or listed in COVERED; both stay few."""
    blocks = [b for doc in DOCS for b in shell_blocks(doc)]
    hardware = [b for b in blocks if b.marker.startswith("hardware")]
    assert len(hardware) <= MAX_HARDWARE, [f"{b.doc}:{b.line}" for b in hardware]
    for b in hardware:
        assert re.search(r"\(.{10,}\)", b.marker), f"{b.doc}:{b.line}: say why it needs hardware: {b.marker!r}"
    other_markers = [f"{b.doc}:{b.line}: {b.marker}" for b in blocks if b.marker and not b.marker.startswith("hardware")]
    assert not other_markers, other_markers
    stale = [k for k in (*COVERED, *EXPECT) if sum(b.has(k) for b in blocks) != 1]
    assert not stale, f"COVERED/EXPECT name blocks that are not (once) in the documents: {stale}"
    assert not [k for k in EXPECT if any(b.has(k) and b.has(c) for b in blocks for c in COVERED)]
    for doc, start in SHORTEN:
        matches = [ln for b in shell_blocks(doc) for ln in b.text.splitlines() if ln.lstrip().startswith(start)]
        assert len(matches) == 1, f"SHORTEN's {start!r} matches {len(matches)} lines of {doc}"
    run = sum(len(to_run(doc)) for doc in DOCS)
    assert run + len(hardware) + len(COVERED) == len(blocks)


# ---------------------------------------------------------------------------------- runner

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _clone(work: Path) -> dict[str, str]:
    """Lay out ``work`` like a clone: examples/ copied (configurations resolve their run logs
    and models from their own folder), tests/data and .venv linked (read only). Returns the
    port replacements, applied to the copied examples."""
    ports = {p: str(_free_port()) for p in PORTS}
    shutil.copytree(ROOT / "examples", work / "examples", ignore=shutil.ignore_patterns("runs", "__pycache__"))
    (work / "tests").mkdir()
    (work / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    (work / ".venv").symlink_to(Path(sys.prefix))
    for f in (work / "examples").rglob("*"):
        if f.is_file() and f.suffix in (".toml", ".py", ".txt"):
            text = f.read_text(encoding="utf-8")
            new = _ports(text, ports)
            if new != text:
                f.write_text(new, encoding="utf-8")
    return ports


def _shorten(b: Block) -> str:
    """The block's text with the options of SHORTEN added to its matching commands (before
    a trailing comment)."""
    out = []
    for line in b.text.splitlines():
        for (doc, start), (args, _) in SHORTEN.items():
            if doc == b.doc and line.lstrip().startswith(start):
                cmd, sep, comment = line.partition(" #")
                line = f"{cmd.rstrip()} {' '.join(args)}" + (f"   #{comment}" if sep else "")
        out.append(line)
    return "\n".join(out) + "\n"


def _ports(text: str, ports: dict[str, str]) -> str:
    for old, new in ports.items():
        text = re.sub(rf"(?<=127\.0\.0\.1:){old}\b", new, text)
    return text


def _session_pids(sid: int) -> list[int]:
    """The processes of session ``sid`` (what the blocks started and left running)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[3]) == sid and fields[0] != "Z":      # session id; zombies are gone
                pids.append(int(d.name))
    return pids


def _cmdline(pid: int) -> str:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return "?"


def _end_session(sid: int, grace_s: float) -> list[str]:
    """Wait ``grace_s`` for the session's processes to end by themselves, then stop them
    (SIGTERM, then SIGKILL). Returns what was still running after the grace."""
    deadline = time.monotonic() + grace_s
    while _session_pids(sid) and time.monotonic() < deadline:
        time.sleep(0.2)
    left = [f"{pid}: {_cmdline(pid)}" for pid in _session_pids(sid)]
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in _session_pids(sid):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 10.0
        while _session_pids(sid) and time.monotonic() < deadline:
            time.sleep(0.1)
    assert not _session_pids(sid), f"processes of the document's shell survived SIGKILL: {_session_pids(sid)}"
    return left


def _tail(path: Path, n: int = 30) -> str:
    lines = path.read_text(errors="replace").splitlines() if path.exists() else []
    return "\n".join(lines[-n:])


def run_doc(doc: str, tmp_path: Path) -> list[tuple[Block, Path]]:
    """Run ``doc``'s shell blocks in order in one bash; returns each block with the stem of
    its output files (``STEM.out``, ``STEM.err``). Fails with the block that failed."""
    blocks = to_run(doc)
    work, state = tmp_path / "clone", tmp_path / "doc-test"
    work.mkdir()
    state.mkdir()
    ports = _clone(work)
    lines = ["set -euo pipefail"]
    for n, b in enumerate(blocks):
        (state / f"b{n}.sh").write_text(_ports(_shorten(b), ports), encoding="utf-8")
        lines += [f'cd "{work}"', f'echo {n} > "{state}/current"',
                  f'source "{state}/b{n}.sh" > "{state}/b{n}.out" 2> "{state}/b{n}.err"',
                  "jobs > /dev/null"]     # bash forgets the ended jobs, as at an interactive prompt: %1 is free again
    lines.append(f'echo done > "{state}/current"')
    (state / "doc.sh").write_text("\n".join(lines) + "\n", encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("AFMCTL_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTHONUNBUFFERED", None)          # as in a user's shell
    current, started, failure = "", time.monotonic(), ""
    with open(state / "bash.err", "wb") as err:
        proc = subprocess.Popen(["bash", str(state / "doc.sh")], cwd=work, env=env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    try:
        while proc.poll() is None:
            time.sleep(0.2)
            now = (state / "current").read_text().strip() if (state / "current").exists() else ""
            if now != current:
                current, started = now, time.monotonic()
            elif current.isdigit() and time.monotonic() - started > TIMEOUT_S:
                failure = f"timed out after {TIMEOUT_S:.0f} s"
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(30.0)
        if proc.returncode != 0 and not failure:
            failure = f"exit status {proc.returncode}"
    finally:
        left = _end_session(proc.pid, grace_s=0.0 if failure else 30.0)
    if failure:
        b = blocks[int(current)] if current.isdigit() else None
        where = f"{doc}:{b.line}" if b else doc
        pytest.fail(f"{where}: the block failed ({failure}):\n{b.text if b else ''}\n"
                    f"--- its stderr (tail):\n{_tail(state / f'b{current}.err')}\n"
                    f"--- its stdout (tail):\n{_tail(state / f'b{current}.out', 10)}\n"
                    f"--- bash:\n{_tail(state / 'bash.err', 5)}", pytrace=False)
    assert current == "done", (current, _tail(state / "bash.err"))
    assert not left, f"{doc}: still running after its last block: {left}"
    return [(b, state / f"b{n}") for n, b in enumerate(blocks)]


def _check_readme_tour(work: Path) -> None:
    """The instrument tour's files: a scanner file with where it came from, its recording,
    the learned table."""
    import json

    import numpy as np
    tour = work / "tour"
    model = json.loads((tour / "scanner.json").read_text())
    prov = model["provenance"]
    assert model["kind"] == "scanner" and model["axes"]["x"]["kind"] == "pi"     # x calibrated (SHORTEN: pi)
    assert prov["device"]["driver"] == "gcs" and "E-727" in prov["device"]["identity"]
    assert prov["recorder_rate_Hz"] == 10000.0 and prov["axes"]["x"]["pieces"] >= 2   # the recorder: 87,381 points a signal
    assert set(prov["validation"]["x"]) == {"raster", "minor loops", "all"}
    assert prov["validation"]["x"]["all"]["max_pct"] < 10.0                     # PI on this scanner: ~2 %
    rec = (tour / "scanner.x-recording.csv").read_text().splitlines()
    assert rec[0] == "t,u,y,v,measured"
    data = np.loadtxt(rec[1:], delimiter=",")
    assert np.ptp(data[:, 2]) > 5000.0                       # the sensor saw the scanner sweep the range
    held = np.flatnonzero(data[:, 4] == 0.0)                 # the holds between the pieces: not measured
    assert held.size and set(np.unique(data[:, 4])) == {0.0, 1.0} and held[0] > 0
    assert np.all(data[held, 1] == data[held - 1, 1])        # ... at the voltage held
    assert 0 < np.max(np.abs(data[:, 3] - data[:, 1])) < 5.0  # the piezo voltage lags the command a little
    # x learned without a creep stage (SHORTEN: pi): every play, the run's too, started
    # AS_RECORDED_REST_S after the play before it ended (the learn's plays, then the run)
    from afmctl.control.learned_after import AS_RECORDED_REST_S
    from afmctl.control.learned_table import load_learned
    from afmctl.control.runlog import RunLogReader
    spacing = load_learned(tour / "line.afmwave").as_recorded
    assert spacing is not None and spacing.axes == ("x",) and spacing.rest_s == AS_RECORDED_REST_S
    plays = [{e["event"]: e["wall_time"] for e in RunLogReader(f).events()}
             for f in sorted((tour / "runs").glob("*.afmlog"))]
    gaps = [b["ramp"] - a["stopped"] for a, b in zip(plays, plays[1:])]
    assert len(gaps) >= 3 and min(gaps) >= AS_RECORDED_REST_S - 0.05, gaps
    assert plays[-1]["ramp"] >= spacing.ended_unix_s + AS_RECORDED_REST_S - 0.05


#: checks of what a document's blocks wrote, run after them (the clone's folder)
AFTER = {"README.md": _check_readme_tour}

RUN_DOCS = [doc for doc in DOCS if to_run(doc)]


@pytest.mark.slow
@pytest.mark.parametrize("doc", RUN_DOCS)
def test_the_documents_shell_blocks_run_as_written(doc, tmp_path):
    text = (ROOT / doc).read_text(encoding="utf-8")
    for block, stem in run_doc(doc, tmp_path):
        printed = stem.with_suffix(".out").read_text(errors="replace") + stem.with_suffix(".err").read_text(
            errors="replace")
        for want in (w for key, wants in EXPECT.items() if block.has(key) for w in wants):
            assert want in text, f"{doc}: no longer states {want!r} (EXPECT, the block at line {block.line})"
            assert want in printed, f"{doc}:{block.line}: printed no {want!r}:\n{printed[-3000:]}"
    if doc in AFTER:
        AFTER[doc](tmp_path / "clone")
