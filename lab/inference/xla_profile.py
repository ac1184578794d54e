"""Where the forward's time goes on the JAX device (lab/tools/profile_xla.py; lab/tools/gpu_check.sh runs it on the
GPU).

For one artifact of an export (and each variant of it the export holds, `ff3d_tf.inference.xla_export.VARIANTS`):
its median latency as `xla_timing.time_forward` takes it, then a profiler trace of `trace_runs` passes whose device
events (GPU kernels; XLA's thunks on a CPU) are summed per HLO instruction of the compiled program. Each instruction
is joined to the program's text: its kind (convolution, matrix product, scatter, gather, reduction, elementwise,
copy) and the model row it computes (the paper table's letters, from the TensorFlow op names in its metadata).
The device's busy time against the latency says how much is launch gaps and host work rather than kernels.
`bake_weights` also times the artifact with its weights compiled in as constants (what a serving engine that freezes
the graph does), and each variant's flow is compared with the plain artifact's on the same inputs.

Like `xla_timing`, nothing here imports TensorFlow.
"""
from __future__ import annotations

import collections
import glob
import os
import re
import tempfile

import numpy as np

from ff3d_tf.inference.xla_artifact import CompiledForward, load_forward
from ff3d_tf.xla_export_dir import ExportFormatError, load_weights, random_inputs, read_manifest
from lab import bench
from lab.inference.xla_timing import _block, time_forward

CATEGORIES = ("convolution", "matrix product", "scatter", "gather", "reduction", "copy", "elementwise", "other")
OTHER_ROW = "other"  # ops whose TensorFlow name is not under a model row (pillar indices, the head's glue)
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = (.*)$")
_OPCODE = re.compile(r"\s([a-z][a-z0-9\-]*)\(")
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_ROW = re.compile(r"^([A-Z][0-9]*)(?:_\d+)?$")
_TEXT_CHARS = 200  # of an instruction's text in the profile (its shape, operands and fusion kind)


def parse_hlo(text: str) -> dict[str, dict]:
    """{instruction name: {"opcode", "target" (a custom call's), "calls" (computations it calls), "op_name",
    "computation"}} of an HLO module's text, and under the key None {computation: [instruction names]}."""
    instructions, computations, current = {}, collections.defaultdict(list), None
    for line in text.splitlines():
        m = _INSTRUCTION.match(line)
        if m is None:
            c = _COMPUTATION.match(line)
            if c is not None:
                current = c.group(1)
            continue
        name, rest = m.groups()
        op = _OPCODE.search(" " + rest)
        target = re.search(r'custom_call_target="([^"]*)"', rest)
        op_name = re.search(r'op_name="([^"]*)"', rest)
        calls = re.findall(r"(?:calls|to_apply|body|condition)=%?([\w.\-]+)", rest)
        instructions[name] = {"opcode": op.group(1) if op else "", "target": target.group(1) if target else "",
                              "calls": calls, "op_name": op_name.group(1) if op_name else "",
                              "computation": current, "text": rest.split(", metadata=")[0][:_TEXT_CHARS]}
        computations[current].append(name)
    return {**instructions, None: dict(computations)}


def _called_opcodes(hlo: dict, name: str, seen=None) -> set[str]:
    """Opcodes (and custom-call targets) of the instruction and of every computation it calls, transitively."""
    seen = set() if seen is None else seen
    info = hlo[name]
    found = {info["opcode"], info["target"]}
    for computation in info["calls"]:
        if computation in seen:
            continue
        seen.add(computation)
        for inner in hlo[None].get(computation, []):
            found |= _called_opcodes(hlo, inner, seen)
    return found


def category(hlo: dict, name: str) -> str:
    """The kind of work an instruction (a fusion: the instructions it fuses) does, one of CATEGORIES."""
    if name not in hlo:
        return "other"
    ops = _called_opcodes(hlo, name)
    targets = " ".join(ops).lower()
    if "convolution" in ops or "conv" in targets:
        return "convolution"
    if "dot" in ops or "gemm" in targets or "matmul" in targets:
        return "matrix product"
    for opcode, kind in (("scatter", "scatter"), ("gather", "gather"), ("reduce", "reduction"),
                         ("reduce-window", "reduction"), ("sort", "other")):
        if opcode in ops:
            return kind
    if ops & {"copy", "transpose"} and not ops - {"copy", "transpose", "parameter", "bitcast", ""}:
        return "copy"
    return "elementwise"


def model_row(hlo: dict, name: str) -> str:
    """The paper table's row (layer letter) whose TensorFlow op an instruction computes; for a fusion without its own
    op name, its fused instructions' most common row; OTHER_ROW when none is a row."""
    rows = collections.Counter()
    stack, seen = [name], set()
    while stack:
        current = stack.pop()
        info = hlo.get(current)
        if info is None or current in seen:
            continue
        seen.add(current)
        first = info["op_name"].split(";")[0].split("/")[0]
        m = _ROW.match(first)
        if m is not None:
            rows[m.group(1)] += 1
            if current == name:
                return m.group(1)
        for computation in info["calls"]:
            stack += hlo[None].get(computation, [])
    return rows.most_common(1)[0][0] if rows else OTHER_ROW


def device_events(xspace_path: str) -> tuple[list[tuple[str, str, float]], str]:
    """[(hlo_op, hlo_module, duration_ns)] of the trace's device work, and where it came from: the GPU planes' stream
    lines when there are any (an event that names no HLO op, a copy say, under its own name), else every host event
    that names an HLO op (XLA's CPU thunks)."""
    from jax.profiler import ProfileData
    profile = ProfileData.from_file(xspace_path)
    gpu = [p for p in profile.planes if p.name.startswith("/device:GPU")]
    planes = gpu or [p for p in profile.planes if p.name.startswith("/host:CPU")]
    events = []
    for plane in planes:
        lines = [line for line in plane.lines if line.name.startswith("Stream")] if gpu else list(plane.lines)
        for line in lines:
            for event in line.events:
                stats = dict(event.stats)
                if "hlo_op" in stats or gpu:
                    events.append((str(stats.get("hlo_op", event.name)), str(stats.get("hlo_module", "")),
                                   float(event.duration_ns)))
    return events, ("GPU stream kernels" if gpu else "CPU thunks")


def trace(fn, runs: int, out_dir: str) -> str:
    """Runs `fn` `runs` times under JAX's profiler, writing under `out_dir`; returns the trace's xspace file."""
    import jax
    with jax.profiler.trace(out_dir):
        for _ in range(runs):
            fn()
    found = glob.glob(os.path.join(out_dir, "**", "*.xplane.pb"), recursive=True)
    if not found:
        raise RuntimeError(f"the profiler wrote no .xplane.pb under {out_dir}")
    return found[0]


def op_profile(compiled, fn, runs: int, top: int = 40) -> dict:
    """Device time per pass of a compiled program: total, by category, by model row and the `top` instructions."""
    text = compiled.as_text()
    hlo = parse_hlo(text)
    module = re.match(r"HloModule\s+([\w.\-]+)", text)
    with tempfile.TemporaryDirectory(prefix="ff3d_xla_profile_") as out_dir:
        events, source = device_events(trace(fn, runs, out_dir))
    if module is not None and any(m == module.group(1) for _, m, _ in events):
        events = [e for e in events if e[1] == module.group(1)]
    per_op = collections.defaultdict(lambda: [0.0, 0])
    for op, _, ns in events:
        per_op[op][0] += ns / runs / 1e6
        per_op[op][1] += 1
    ops = sorted(({"op": op, "ms": ms, "calls_per_pass": n / runs, "category": category(hlo, op),
                   "row": model_row(hlo, op), "hlo": hlo.get(op, {}).get("text", "")}
                  for op, (ms, n) in per_op.items()), key=lambda r: -r["ms"])
    by = {}
    for key in ("category", "row"):
        totals = collections.Counter()
        for row in ops:
            totals[row[key]] += row["ms"]
        by[key] = dict(totals.most_common())
    return {"source": source, "trace_runs": runs, "busy_ms": float(sum(r["ms"] for r in ops)),
            "kernels_per_pass": float(sum(r["calls_per_pass"] for r in ops)), "by_category": by["category"],
            "by_row": by["row"], "top_ops": ops[:top], "cost_analysis": cost_analysis(compiled)}


def cost_analysis(compiled) -> dict:
    """XLA's count of the program's floating-point operations and bytes accessed (None where the backend gives none)."""
    try:
        cost = compiled.cost_analysis()
    except Exception:  # noqa: BLE001  (backends without an analysis raise their own errors)
        return {"flops": None, "bytes_accessed": None}
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return {"flops": cost.get("flops"), "bytes_accessed": cost.get("bytes accessed")}


class BakedForward(CompiledForward):
    """An artifact compiled with its weights as constants of the program (XLA folds what depends on them alone: the
    precision casts, the BatchNorm's scale and shift)."""

    def __init__(self, exported, weights: list[np.ndarray]):
        import jax
        self.device = jax.devices()[0]
        self.weights = []
        constants = [np.asarray(w) for w in weights]
        avals = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals[len(weights):]]
        jitted = jax.jit(lambda *inputs: exported.call(*constants, *inputs))
        self.compiled, self.compile_s = bench.elapsed(lambda: jitted.lower(*avals).compile())


def _entries(manifest: dict, points: int, precision: str, variants) -> list[tuple[str, dict]]:
    """[(variant name, "" for the plain artifact), manifest entry] of the batch-1 forward at `points`: the plain
    artifact, then `variants` (an error where one is missing), or when None every variant exported at that size."""
    def pick(entries, what):
        for entry in entries:
            if entry["points"] == points and entry["precision"] == precision and entry["batch_size"] == 1:
                return entry
        raise ExportFormatError(f"no {what} forward of {points} points in {precision} at batch 1 in the export")
    chosen = [("", pick(manifest["artifacts"], "plain"))]
    held = manifest.get("variants", {})
    for name in variants or []:
        if name not in held:
            raise ExportFormatError(f"the export has no variant {name!r} (it has: {', '.join(held) or 'none'})")
        chosen.append((name, pick(held[name], f"variant {name}")))
    if variants is None:  # every variant exported at this size
        chosen += [(name, entry) for name, entries in held.items() for entry in entries
                   if (entry["points"], entry["precision"], entry["batch_size"]) == (points, precision, 1)]
    return chosen


def profile_export(export_dir: str, points: int, precision: str, runs: int, warmup: int, trace_runs: int,
                   variants=None, bake_weights: bool = False, seed: int = 0, log=print) -> list[dict]:
    """One row per program (the plain artifact, its weights baked in when asked, then each variant of the export at
    `points` / `precision`, all when `variants` is None): latency, flow against the plain artifact's, op profile."""
    manifest = read_manifest(export_dir)
    weights = load_weights(export_dir, manifest)
    rows, baseline = [], None
    for name, entry in _entries(manifest, points, precision, variants):
        exported = load_forward(export_dir, entry, len(weights))
        programs = [(name or "plain", CompiledForward)] + ([("plain, weights baked in", BakedForward)]
                                                           if bake_weights and not name else [])
        for label, kind in programs:
            forward = kind(exported, weights)
            inputs = random_inputs(manifest, entry, np.random.default_rng(seed))
            flow = forward.numpy(inputs)["flow_mps"]
            baseline = flow if baseline is None else baseline
            device_inputs = forward.on_device(inputs)
            row = {"program": label, "points": points, "padded_points": entry["padded_points"],
                   "precision": precision, **time_forward(forward, inputs, runs, warmup),
                   "max_abs_flow_diff_vs_plain_mps": float(np.abs(flow - baseline).max()),
                   "flow_scale_mps": float(np.abs(baseline).max()),
                   "profile": _profile_or_error(forward, device_inputs, trace_runs)}
            rows.append(row)
            log(describe(row))
    return rows


def _profile_or_error(forward, device_inputs, trace_runs: int) -> dict:
    """`op_profile`, or {"error": why} when the profiler fails (no tracing library on the machine, say): the latency
    rows are kept either way."""
    try:
        return op_profile(forward.compiled, lambda: _block(forward(device_inputs)), trace_runs)
    except Exception as e:  # noqa: BLE001  (the profiler's own errors: the timing row stays)
        return {"error": f"{type(e).__name__}: {e}"}


def describe(row: dict) -> str:
    p = row["profile"]
    if "error" in p:
        return (f"{row['program']} {row['points']:,} points {row['precision']}: median {row['median_ms']:.3f} ms; "
                f"no profile: {p['error']}")
    kinds = ", ".join(f"{k} {v:.3f}" for k, v in list(p["by_category"].items())[:4])
    return (f"{row['program']} {row['points']:,} points {row['precision']}: median {row['median_ms']:.3f} ms, device "
            f"busy {p['busy_ms']:.3f} ms in {p['kernels_per_pass']:.0f} {p['source']} ({kinds}); flow vs plain "
            f"{row['max_abs_flow_diff_vs_plain_mps']:.2g} m/s")


def profile_table(rows: list[dict], top: int = 12) -> str:
    """Markdown: the programs side by side, then the first row's time by model row and its largest instructions."""
    lines = ["| program | points | precision | median ms | device busy ms | kernels | convolution ms | flow vs plain "
             "(m/s) |", "|---|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        p = r["profile"]
        if "error" in p:
            lines.append(f"| {r['program']} | {r['points']:,} | {r['precision']} | {r['median_ms']:.3f} | no profile: "
                         f"{p['error'][:60]} | | | {r['max_abs_flow_diff_vs_plain_mps']:.2g} |")
            continue
        lines.append(f"| {r['program']} | {r['points']:,} | {r['precision']} | {r['median_ms']:.3f} | "
                     f"{p['busy_ms']:.3f} | {p['kernels_per_pass']:.0f} | "
                     f"{p['by_category'].get('convolution', 0.0):.3f} | {r['max_abs_flow_diff_vs_plain_mps']:.2g} |")
    if rows and "error" not in rows[0]["profile"]:
        p = rows[0]["profile"]
        lines += ["", f"{rows[0]['program']}: device ms per pass by model row", "",
                  "| row | ms |", "|---|---:|"] + [f"| {k} | {v:.3f} |" for k, v in p["by_row"].items()]
        lines += ["", "| instruction | category | row | ms | calls |", "|---|---|---|---:|---:|"]
        lines += [f"| {o['op']} | {o['category']} | {o['row']} | {o['ms']:.4f} | {o['calls_per_pass']:g} |"
                  for o in p["top_ops"][:top]]
    return "\n".join(lines)
