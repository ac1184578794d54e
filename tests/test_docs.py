"""The README and docs/ stay true to the repository.

- every relative link of README.md, data/README.md and docs/*.md leads to a file (and a heading, for `#anchor`);
- every repository path they name in code (`tools/train.py`, `configs/...yaml`, `benchmarks/...json`, ...) exists;
- every `ff3d_tf.module.name` or `lab.module.name` (and `module.NAME` of a module whose file name is unique) is
  defined, read with `ast` (nothing is imported); every config key (`train.peer_timeout_s`) is a field of the config's
  dataclasses;
- every tool in tools/ and lab/tools/ is named somewhere;
- every measured figure is its JSON's: the tables of docs/benchmarks.md are rendered here from benchmarks/*.json
  (`TABLES`) and must appear in the doc exactly as rendered, each figure quoted in prose is formatted from its JSON
  (`QUOTES`), docs/benchmarks.md holds no other table and no other number with a unit; the walk through one training
  step (docs/architecture.md) states the lines and files it spans, counted here.

After a benchmark is rerun, `python tests/test_docs.py` prints every table and quote as the docs must show them.
"""
from __future__ import annotations

import ast
import dataclasses
import fnmatch
import functools
import glob
import json
import math
import os
import re
from typing import Callable

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))  # the checkout, also under Bazel
DOCS_PAGES = ("architecture", "bazel", "benchmarks", "datasets", "deployment", "label_free", "training")
BENCHMARKS_DOC = "docs/benchmarks.md"
REPO_DIRS = ("ff3d_tf", "lab", "tools", "configs", "benchmarks", "tests", "bazel", "data", "docs", "third_party")
PACKAGES = ("ff3d_tf", "lab")  # the Python packages whose modules and names the docs may name


def doc_files() -> list[str]:
    return ["README.md", "data/README.md"] + [f"docs/{p}.md" for p in DOCS_PAGES]


@functools.cache
def read(rel: str) -> str:
    with open(os.path.join(ROOT, rel), encoding="utf-8") as f:
        return f.read()


# --- Markdown: code, links, headings ------------------------------------------------------------------------------

FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.M | re.S)
CODE_SPAN = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"(?<!!)\[[^\]\n]*\]\(([^)\s]+)\)")


def code_texts(text: str) -> list[str]:
    """The fenced blocks and the inline code spans of a Markdown text."""
    blocks = [m.group(0) for m in FENCE.finditer(text)]
    prose = FENCE.sub("", text)
    indented = [line for line in prose.splitlines() if line.startswith("    ") and line.strip()]
    return blocks + indented + CODE_SPAN.findall(prose)


def links(text: str) -> list[str]:
    return LINK.findall(CODE_SPAN.sub("", FENCE.sub("", text)))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (but - and _), spaces to -."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(text: str) -> set[str]:
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", FENCE.sub("", text), re.M)}


def test_slug_and_code_parsing():
    assert slug("Label-free training (ZeroFlow)") == "label-free-training-zeroflow"
    assert slug("`make test` and the CPU") == "make-test-and-the-cpu"
    text = ("a `x/y.py` b\n```\ncmd tools/a.py\n```\n[l](docs/b.md#c) ![img](p.png) `[no](link.md)`\n"
            "    indented tools/c.py\n")
    assert code_texts(text) == ["```\ncmd tools/a.py\n```", "    indented tools/c.py", "x/y.py", "[no](link.md)"]
    assert links(text) == ["docs/b.md#c"]


def test_the_docs_pages_exist():
    assert sorted(os.path.basename(p)[:-3] for p in glob.glob(os.path.join(ROOT, "docs", "*.md"))) == \
        sorted(DOCS_PAGES)


def test_readme_is_short():
    assert len(read("README.md").splitlines()) <= 250


@pytest.mark.parametrize("doc", doc_files())
def test_links_lead_to_files_and_headings(doc):
    here = os.path.dirname(os.path.join(ROOT, doc))
    broken = []
    for target in links(read(doc)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        full = os.path.normpath(os.path.join(here, path)) if path else os.path.join(ROOT, doc)
        if not os.path.exists(full):
            broken.append(f"{target}: no such file")
        elif anchor and full.endswith(".md") and anchor not in anchors(read(os.path.relpath(full, ROOT))):
            broken.append(f"{target}: no heading #{anchor}")
    assert not broken, f"{doc}: {broken}"


# --- Paths, symbols and config keys named in code -----------------------------------------------------------------

PATH = re.compile(r"(?<![\w./~:$-])((?:%s)/[\w./{},*<>-]*)" % "|".join(REPO_DIRS))


def named_paths(text: str) -> list[str]:
    """Repository paths in the code of a doc; `a/{b,c}.py` gives both; templates (`<name>`, `*`) are left out."""
    found = []
    for code in code_texts(text):
        for raw in PATH.findall(code):
            raw = raw.rstrip(".,;:")
            if any(c in raw for c in "*<>"):
                continue
            brace = re.search(r"\{([^{}]*)\}", raw)
            found += [raw[:brace.start()] + alt + raw[brace.end():] for alt in brace.group(1).split(",")] \
                if brace else [raw]
    return found


@pytest.mark.parametrize("doc", doc_files())
def test_named_paths_exist(doc):
    missing = sorted({p for p in named_paths(read(doc)) if not os.path.exists(os.path.join(ROOT, p))})
    assert not missing, f"{doc} names paths that do not exist: {missing}"


def _top_level_names(body: list[ast.stmt]) -> dict[str, ast.AST]:
    """Names a module or class body defines (functions, classes, assignments, imports), `if`/`try` blocks included."""
    names = {}
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names[node.name] = node
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                for t in ast.walk(target):
                    if isinstance(t, ast.Name):
                        names[t.id] = node
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names[node.target.id] = node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                names[(alias.asname or alias.name).split(".")[0]] = node
        elif isinstance(node, (ast.If, ast.Try)):
            for block in (node.body, getattr(node, "orelse", []), getattr(node, "finalbody", []),
                          *[h.body for h in getattr(node, "handlers", [])]):
                names.update(_top_level_names(block))
    return names


@functools.cache
def module_tree(rel: str) -> ast.Module:
    return ast.parse(read(rel), rel)


def module_file(dotted: str) -> str | None:
    """ff3d_tf.a.b -> ff3d_tf/a/b.py or ff3d_tf/a/b/__init__.py (lab.a.b likewise), None if neither exists."""
    base = dotted.replace(".", "/")
    for rel in (base + ".py", base + "/__init__.py"):
        if os.path.isfile(os.path.join(ROOT, rel)):
            return rel
    return None


def symbol_problem(dotted: str) -> str | None:
    """None if `ff3d_tf.module[.name[.member]]` (or `lab.module...`) exists, else what is missing."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        rel = module_file(".".join(parts[:cut]))
        if rel:
            break
    else:
        return f"{dotted}: no module"
    names = parts[cut:]
    if not names:
        return None
    scope, where = _top_level_names(module_tree(rel).body), rel
    for depth, name in enumerate(names[:2]):
        if name not in scope:
            return f"{dotted}: {name} is not defined in {where}"
        node = scope[name]
        if not isinstance(node, ast.ClassDef):
            return None  # a function or value: its attributes are not checked
        scope, where = _top_level_names(node.body), f"{rel}:{name}"
    return None


@functools.cache
def unique_module_basenames() -> dict[str, str]:
    """{file name without .py: dotted module} for the ff3d_tf and lab modules whose file name no other module shares."""
    seen: dict[str, list[str]] = {}
    for path in [p for package in PACKAGES for p in glob.glob(os.path.join(ROOT, package, "**", "*.py"),
                                                                recursive=True)]:
        rel = os.path.relpath(path, ROOT)
        if not rel.endswith("__init__.py"):
            seen.setdefault(os.path.basename(rel)[:-3], []).append(rel[:-3].replace("/", "."))
    return {k: v[0] for k, v in seen.items() if len(v) == 1}


@functools.cache
def config_fields() -> dict[str, set[str]]:
    """{section: its field names} of `ff3d_tf.config.ExperimentConfig`, read from the source."""
    scope = _top_level_names(module_tree("ff3d_tf/config.py").body)
    sections = {}
    for node in scope["ExperimentConfig"].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.annotation, ast.Name):
            cls = scope[node.annotation.id]
            sections[node.target.id] = {n.target.id for n in cls.body
                                        if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
            sections[node.target.id] |= {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}  # properties
    return sections


FULL_SYMBOL = re.compile(r"(?<![\w./])((?:ff3d_tf|lab)(?:\.[A-Za-z_]\w*)+)")
FILE_SUFFIXES = {"py", "json", "csv", "yaml", "md", "txt", "onnx", "npz", "npy", "rrd", "zip", "feather", "pcd", "ply",
                 "bin", "sh", "png", "bzl", "tfrecord", "jaxexport", "partial"}
SHORT_SYMBOL = re.compile(r"(?<![\w./=-])([a-z_][a-z0-9_]*)\.([A-Za-z_]\w*)(?![\w/]|\.\w)")


def symbol_problems(text: str) -> list[str]:
    problems = []
    for code in code_texts(text):
        for dotted in FULL_SYMBOL.findall(code):
            if problem := symbol_problem(dotted):
                problems.append(problem)
        for first, name in SHORT_SYMBOL.findall(code):
            if name in FILE_SUFFIXES:
                continue  # metrics.json, model.onnx: a file name
            sections, modules = config_fields(), unique_module_basenames()
            if first not in sections and first not in modules:
                continue  # tf.where, np.float32, a file name: not the project's
            if name in sections.get(first, ()):
                continue
            if first in modules and symbol_problem(f"{modules[first]}.{name}") is None:
                continue
            problems.append(f"{first}.{name}: " + ("no such config key" if first in sections else
                                                  f"not defined in {modules[first]}"))
    return problems


def test_symbol_and_config_checks_find_what_is_missing():
    assert symbol_problem("ff3d_tf.model.step.adam_update") is None
    assert symbol_problem("ff3d_tf.training.trainer.Trainer.step") is None
    assert symbol_problem("ff3d_tf.model.step.no_such_function") is not None
    assert symbol_problem("ff3d_tf.no_such_module") is not None
    assert symbol_problems("`train.peer_timeout_s`, `geometry.POSE_RIGIDITY_TOLERANCE`, `tf.where`, "
                           "`metrics.json`") == []
    assert len(symbol_problems("`train.no_such_key` and `geometry.POSE_TOLERANCE`")) == 2


@pytest.mark.parametrize("doc", doc_files())
def test_named_symbols_and_config_keys_exist(doc):
    problems = sorted(set(symbol_problems(read(doc))))
    assert not problems, f"{doc}: {problems}"


def test_every_tool_is_documented():
    text = "\n".join(read(d) for d in doc_files())
    tools = [f"{d}/{n}" for d in ("tools", "lab/tools") for n in sorted(os.listdir(os.path.join(ROOT, d)))
             if n.endswith((".py", ".sh")) and not n.startswith("_")]
    assert [t for t in tools if t not in text] == []


def undocumented_files(names: list[str], text: str) -> list[str]:
    """The names that `text` names neither whole nor through a pattern of its own (`xla_latency_*.json`)."""
    patterns = [p for p in re.findall(r"[\w*.-]+", text) if "*" in p]
    return [n for n in names if n not in text and not any(fnmatch.fnmatchcase(n, p) for p in patterns)]


def test_undocumented_files_reads_names_and_patterns():
    text = "see `benchmarks/a.json` and `benchmarks/gpu_*.json`"
    assert undocumented_files(["a.json", "gpu_h200.json", "b.json", "xgpu_1.json"], text) == ["b.json", "xgpu_1.json"]


def test_every_benchmark_is_documented():
    """A JSON under benchmarks/ that no doc names is a figure no reader finds (history lives in git)."""
    text = "\n".join(read(d) for d in doc_files())
    names = sorted(n for n in os.listdir(os.path.join(ROOT, "benchmarks")) if n.endswith(".json"))
    assert undocumented_files(names, text) == []


# --- Figures -------------------------------------------------------------------------------------------------------

@functools.cache
def source(name: str):
    """A benchmarks/*.json file by name, or the literal constants of a Python file (`ff3d_tf/...py`, `lab/...py`)."""
    if name.endswith(".py"):
        return {k: ast.literal_eval(v.value) for k, v in _top_level_names(module_tree(name).body).items()
                if isinstance(v, ast.Assign) and _is_literal(v.value)}
    with open(os.path.join(ROOT, "benchmarks", name)) as f:
        return json.load(f)


def _is_literal(node) -> bool:
    try:
        ast.literal_eval(node)
        return True
    except ValueError:
        return False


def lookup(data, path):
    """The value at "a/b/c": a key may itself hold "/" ("auto/float32"; the shortest key that exists is taken, or
    give the path as a tuple of keys); a list item by its fields: "latency[points=32000,precision=tf32]"; a key that
    is not in a dict is also tried as an int."""
    parts = list(path) if isinstance(path, tuple) else path.split("/")
    while parts:
        part = parts.pop(0)
        key, _, select = part.partition("[")
        if key:
            if isinstance(data, dict) and not isinstance(path, tuple):
                while key not in data and parts and not key.lstrip("-").isdigit():
                    more, _, select = parts.pop(0).partition("[")
                    key = f"{key}/{more}"
            if isinstance(data, dict) and key not in data and key.lstrip("-").isdigit():
                key = int(key)
            data = data[key]
        if select:
            wanted = dict(kv.split("=") for kv in select.rstrip("]").split(","))
            matches = [item for item in data if all(str(item.get(k)) == v for k, v in wanted.items())]
            assert len(matches) == 1, f"{path}: {len(matches)} items match"
            data = matches[0]
    return data


@dataclasses.dataclass(frozen=True)
class V:
    """A figure: the value at `path` of `file` (benchmarks/<file>, or a Python file's constant), formatted by `fmt`."""
    file: str
    path: str | tuple
    fmt: str = "{}"

    def value(self):
        return lookup(source(self.file), self.path)

    def text(self) -> str:
        return self.fmt.format(self.value())


@dataclasses.dataclass(frozen=True)
class Calc:
    """A figure computed from figures (a ratio, a sum), formatted by `fmt`."""
    fmt: str
    fn: Callable
    args: tuple

    def value(self):
        return self.fn(*[a.value() for a in self.args])

    def text(self) -> str:
        return self.fmt.format(self.value())


def ratio(fmt: str, a, b) -> Calc:
    return Calc(fmt, lambda x, y: x / y, (a, b))


def on_cpu(file: str, cpu: str = "cpu") -> Calc:
    """The CPU a JSON was measured on, as `ff3d_tf.cpu.describe()` recorded it under `cpu`: "NAME (N cores,
    family/model F/M)"."""
    return Calc("{}", lambda name, count, family_model: f"{name} ({count} cores, family/model {family_model})",
                (V(file, f"{cpu}/model_name"), V(file, f"{cpu}/cpu_count"), V(file, f"{cpu}/family_model")))


def render(cell) -> str:
    return cell if isinstance(cell, str) else cell.text()


@dataclasses.dataclass(frozen=True)
class Quote:
    """Figures in a sentence of `doc`: `template` with each {} replaced by a figure's text."""
    doc: str
    template: str
    figures: tuple

    def text(self) -> str:
        return self.template.format(*[render(f) for f in self.figures])


@dataclasses.dataclass(frozen=True)
class Table:
    """A table of `doc`, rendered from its figures: a caption line (naming the machine), the header, the rows."""
    doc: str
    caption: Quote
    header: tuple
    align: str  # one character per column: l or r
    rows: tuple

    def rows_text(self) -> str:
        lines = ["| " + " | ".join(self.header) + " |",
                 "|" + "|".join("---:" if a == "r" else "---" for a in self.align) + "|"]
        lines += ["| " + " | ".join(render(c) for c in row) + " |" for row in self.rows]
        return "\n".join(lines)

    def text(self) -> str:
        return f"{self.caption.text()}\n\n{self.rows_text()}"


B = BENCHMARKS_DOC


def _ms(file, path):
    return V(file, path, "{:,.0f} ms")


# -- inference on CPU by compile mode (benchmark_latency.py)
_LAT = "latency_cpu.json"
_LAT_CAPTION = Quote(B, "`benchmarks/latency_cpu.json`, paper config, batch 1, median of {} calls, {}:",
                     (V(_LAT, "latency/32000/auto/runs"), on_cpu(_LAT)))
_MODES = ("auto", "hybrid", "xla", "none")
LATENCY_TABLE = Table(B, _LAT_CAPTION, ("`model.compile`", "forward, 32,000 points", "forward, 1,000,000 points",
                                        "training step, 32,000 points"), "lrrr",
                      tuple((f"`{m}`", _ms(_LAT, f"latency/32000/{m}/median_ms"),
                             _ms(_LAT, f"latency/1000000/{m}/median_ms"), _ms(_LAT, f"train_step/{m}/median_ms"))
                            for m in _MODES))

# -- bfloat16 on three CPUs (benchmark_bf16.py)
_AMD, _AMX = "bf16_cpu_amd.json", "bf16_cpu_amx.json"
_BF16_FILES = (_AMD, _AMX, "bf16_cpu.json")


def _cpu_name(file):
    return Calc("{}", lambda name, flags: f"{name} ({', '.join(flags)})",
                (V(file, "cpu/model_name"), V(file, "cpu/bf16_flags")))


def _bf16_cell(file, points):
    return Calc("{}", lambda a, b, s: f"{a:,.0f} -> {b:,.0f} ms ({s:.2f}x)",
                (V(file, f"latency/latency/{points}/auto/float32/median_ms"),
                 V(file, f"latency/latency/{points}/auto/bfloat16/median_ms"),
                 V(file, f"summary/inference_speedup_bfloat16_median/{points}")))


BF16_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_bf16.py`, paper config, compile mode hybrid, medians of {} calls, {} cores of "
                "each CPU:", (V(_AMD, "latency/latency/32000/auto/float32/runs"), V(_AMD, "cpu/cpu_count"))),
    ("CPU (its bfloat16 flags)", "`auto` picks", "inference, 32,000 points", "inference, 1,000,000 points",
     "training step, 32,000 points: speed-up", "file"), "llrrrl",
    tuple((_cpu_name(f), V(f, "cpu/auto_resolves_to"), _bf16_cell(f, 32000), _bf16_cell(f, 1000000),
           V(f, "summary/train_step_speedup_bfloat16_median", "{:.2f}x"), f"`benchmarks/{f}`")
          for f in _BF16_FILES))

# -- memory between calls (profile_memory.py)
_MEM = "memory_cpu.json"
MEMORY_TABLE = Table(
    B, Quote(B, "`lab/tools/profile_memory.py`, paper config, {} points, batch 1, resident memory (GB) of a process "
                "on {}; CPU time relative to the default:",
             (V(_MEM, "points", "{:,}"), on_cpu(_MEM))),
    ("allocator", "between training steps", "between inference calls", "CPU time per step",
     "CPU time per inference call"), "lrrrr",
    (("default (oneDNN's pool)", V(_MEM, "variants/tf_bfc_pool/summary/train/rss_between_gb", "{:.2f}"),
      V(_MEM, "variants/tf_bfc_pool/summary/infer/rss_between_gb", "{:.2f}"), "1", "1"),
     ("`TF_ONEDNN_USE_SYSTEM_ALLOCATOR=1`",
      V(_MEM, "variants/system_allocator/summary/train/rss_between_gb", "{:.2f}"),
      V(_MEM, "variants/system_allocator/summary/infer/rss_between_gb", "{:.2f}"),
      ratio("{:.2f}", V(_MEM, "variants/system_allocator/summary/train/median_cpu_ms"),
            V(_MEM, "variants/tf_bfc_pool/summary/train/median_cpu_ms")),
      ratio("{:.2f}", V(_MEM, "variants/system_allocator/summary/infer/median_cpu_ms"),
            V(_MEM, "variants/tf_bfc_pool/summary/infer/median_cpu_ms")))))

# -- ONNX (benchmark_onnx.py)
_ONNX = "onnx_cpu.json"
ONNX_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_onnx.py`, paper config, random weights, {} points, medians of {} calls, "
                "onnxruntime {} with {} threads, {}:",
             (V(_ONNX, "points", "{:,}"), V(_ONNX, "runs"), V(_ONNX, "versions/onnxruntime"),
              V(_ONNX, "onnxruntime_intra_op_threads"), on_cpu(_ONNX))),
    ("runtime", "median", "over TensorFlow", "largest flow difference from TensorFlow"), "lrrr",
    (("TensorFlow (SavedModel forward)", _ms(_ONNX, "latency/tensorflow/median_ms"), "1", "0"),
     ("onnxruntime, `loop`", _ms(_ONNX, "latency/onnxruntime_loop/median_ms"),
      V(_ONNX, "ratios_over_tensorflow/onnxruntime_loop", "{:.2f}"),
      V(_ONNX, "accuracy/onnxruntime_loop/max_abs_flow_diff_mps", "{:.1e} m/s")),
     ("onnxruntime, `single_chunk`", _ms(_ONNX, "latency/onnxruntime_single_chunk/median_ms"),
      V(_ONNX, "ratios_over_tensorflow/onnxruntime_single_chunk", "{:.2f}"),
      V(_ONNX, "accuracy/onnxruntime_single_chunk/max_abs_flow_diff_mps", "{:.1e} m/s"))))

# -- portable XLA on an H200 (run_xla.py via gpu_check.sh)
_GPU = "xla_latency_gpu.json"
_P100 = "lab/inference/xla_timing.py"


def _gpu_ms(points, precision):
    return V(_GPU, f"latency[points={points},precision={precision}]/median_ms", "{:.2f} ms")


def _speedup(points, precision):
    return ratio("{:.0f}x", V(_P100, f"PAPER_P100_LATENCY_MS/{points}"),
                 V(_GPU, f"latency[points={points},precision={precision}]/median_ms"))


GPU_FORWARD_TABLE = Table(
    B, Quote(B, "`lab/tools/gpu_check.sh` on an {} (jax {}), random weights, medians of {} forward passes after {} "
                "warm-up, clouds on the device:",
             (V(_GPU, "device"), V(_GPU, "jax"), V(_GPU, "latency[points=32000,precision=tf32]/runs"),
              V(_GPU, "latency[points=32000,precision=tf32]/warmup"))),
    ("points", "float32 (HIGHEST)", "tf32", "bfloat16", "paper, P100", "tf32 speed-up", "bfloat16 speed-up"),
    "rrrrrrr",
    tuple((f"{p:,}", _gpu_ms(p, "float32"), _gpu_ms(p, "tf32"), _gpu_ms(p, "bfloat16"),
           V(_P100, f"PAPER_P100_LATENCY_MS/{p}", "{} ms"), _speedup(p, "tf32"), _speedup(p, "bfloat16"))
          for p in (32000, 1000000)))


def _step(batch, precision, key, fmt):
    return V(_GPU, f"train_step[batch_size={batch},precision={precision}]/{key}", fmt)


GPU_TRAIN_TABLE = Table(
    B, Quote(B, "The training step (forward, loss, backward, Adam) on the same {}, {} points a cloud, medians of "
                "{} steps:", (V(_GPU, "device"), V(_GPU, "train_step[batch_size=1,precision=tf32]/points", "{:,}"),
                              V(_GPU, "train_step[batch_size=1,precision=tf32]/runs"))),
    ("batch", "precision", "ms per step", "ms per pair", "pairs/s"), "rlrrr",
    tuple((str(b), p, _step(b, p, "median_ms", "{:.1f}"), _step(b, p, "ms_per_pair", "{:.1f}"),
           _step(b, p, "pairs_per_s", "{:.0f}")) for p in ("float32", "tf32", "bfloat16") for b in (1, 8)))

# -- input (benchmark_input.py, benchmark_training.py)
_IN = "input_cpu.json"


def _rate(density, key):
    return V(_IN, f"densities/{density}/per_core_per_s/1/{key}", "{:.1f}")


INPUT_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_input.py`, the trainer's whole input (read, pair, shuffle, batch, pad), pairs/s "
                "on 1 core of {}; synthetic WOD segments at WOD's density ({} points a frame) and at "
                "the synthetic default's ({}):",
             (on_cpu(_IN), V(_IN, "densities/wod/sizes/points_per_frame", "{:,}"),
              V(_IN, "densities/synthetic/sizes/points_per_frame", "{:,}"))),
    ("input", "WOD density", "synthetic default"), "lrr",
    (("decode WOD frames on the fly", _rate("wod", "decode_pair_batch"), _rate("synthetic", "decode_pair_batch")),
     ("pair records, exact", _rate("wod", "records_exact"), _rate("synthetic", "records_exact")),
     ("pair records, compact", _rate("wod", "records_compact"), _rate("synthetic", "records_compact"))))


def _av2_rate(key):
    return V(_IN, f"av2/per_core_per_s/1/{key}", "{:.1f}")


AV2_INPUT_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_input.py --av2`, synthetic Argoverse 2 logs at {} points a sweep, pairs/s on 1 "
                "core of {}:", (V(_IN, "av2/points_per_sweep", "{:,}"), on_cpu(_IN, "av2/cpu"))),
    ("step", "pairs/s"), "lr",
    (("labels made in the input pipeline (no records)", _av2_rate("labels_in_pipeline")),
     ("trainer's input from records, exact", _av2_rate("records_exact")),
     ("trainer's input from records, compact", _av2_rate("records_compact")),
     ("writing records (`tools/write_pair_records.py --source av2`), exact", _av2_rate("write_exact"))))

_TR = "training_cpu.json"
TRAINING_INPUT_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_training.py`, paper config, batch 1, synthetic WOD segments at full size "
                "({} points a cloud), {}:",
             (V(_TR, "input[cores=1]/mean_points_t0", "{:,.0f}"), on_cpu(_TR))),
    ("measurement", "result"), "lr",
    (("training input alone, 1 core", V(_TR, "input[cores=1]/pairs_per_s", "{:.1f} pairs/s")),
     ("training input alone, 2 cores", V(_TR, "input[cores=2]/pairs_per_s", "{:.1f} pairs/s")),
     ("frames decoded for 6 pairs of 8 frames", V(_TR, "decode_count/decodes")),
     ("training step on a batch held in memory", V(_TR, "train_step/mean_step_s", "{:.1f} s")),
     ("training step fed by the real input", V(_TR, "end_to_end/mean_step_s", "{:.1f} s"))))


def _cores(precision, batch):
    return Calc("{}", lambda per_s, core: math.ceil(per_s / core),
                (V(_GPU, f"train_step[batch_size={batch},precision={precision}]/pairs_per_s"),
                 V(_TR, "input[cores=1]/pairs_per_s")))


SIZING_TABLE = Table(
    B, Quote(B, "Decoding cores an {} needs at the 1-core rate above (pairs/s it trains, divided by that rate, "
                "rounded up):", (V(_GPU, "device"),)),
    ("training step", "pairs/s", "decoding cores"), "lrr",
    tuple((f"{p}, batch {b}", _step(b, p, "pairs_per_s", "{:.0f}"), _cores(p, b))
          for p, b in (("float32", 8), ("tf32", 1), ("tf32", 8), ("bfloat16", 8))))

# -- NSFP speed (benchmark_nsfp.py)
_NSFP = "nsfp_cpu.json"
NSFP_SPEED_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_nsfp.py`, the job's fit (`nsfp.MEASURED_FIT_OPTIONS`), {} points a cloud, "
                "{} ({} cores):", (V(_NSFP, "speed/points", "{:,}"), V(_NSFP, "machine/model_name"),
                                   V(_NSFP, "machine/cpu_count"))),
    ("Chamfer distances by", "seconds per Adam step", "grids of both clouds"), "lrr",
    (("the distance transform (default)", V(_NSFP, "speed/distance_transform/seconds_per_step", "{:.2f} s"),
      V(_NSFP, "speed/distance_transform/grid_build_s_both_clouds", "{:.2f} s")),
     ("exact nearest neighbours (`--exact_chamfer`)",
      V(_NSFP, "speed/exact_nearest_neighbours/seconds_per_step", "{:.2f} s"), "none")))

# -- NSFP pseudo-labels of the Argoverse 2 sample through the tools (benchmark_nsfp.py, section av2_sample)
_AV2S = "av2_sample"


def _av2_score(who, key, fmt):
    return V(_NSFP, f"{_AV2S}/{who}/{key}", fmt)


NSFP_QUALITY_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_nsfp.py` on `data/av2_sample_log` (one real pair): `tools/write_pair_records.py "
                "--source av2`, then `tools/pseudo_label.py` with its defaults, whose own scores by the challenge's "
                "arithmetic are these ({} points scored; {}, {} cores):",
             (V(_NSFP, f"{_AV2S}/evaluated_points", "{:,}"), V(_NSFP, "machine/model_name"),
              V(_NSFP, "machine/cpu_count"))),
    ("", "three-way EPE", "foreground dynamic EPE", "bucketed normalized dynamic EPE"), "lrrr",
    (("NSFP pseudo-labels", _av2_score("nsfp", "three_way/mean_epe_m", "{:.3f} m"),
      _av2_score("nsfp", "three_way/fg_dynamic_epe_m", "{:.3f} m"),
      _av2_score("nsfp", "bucketed/mean_dynamic_norm_epe", "{:.3f}")),
     ("zero flow", _av2_score("zero_flow", "three_way/mean_epe_m", "{:.3f} m"),
      _av2_score("zero_flow", "three_way/fg_dynamic_epe_m", "{:.3f} m"),
      _av2_score("zero_flow", "bucketed/mean_dynamic_norm_epe", "{:.3f}")),
     ("the bar (at most)", V(_NSFP, (_AV2S, "bar_at_most", "three_way/mean_epe_m"), "{} m"), "",
      V(_NSFP, (_AV2S, "bar_at_most", "bucketed/mean_dynamic_norm_epe")))))

# -- NSFP at highway speeds (benchmark_nsfp_speed.py)
_NS = "nsfp_speed.json"
_LF = "docs/label_free.md"
_NS_ROWS = (("the job's fit", "tune/baseline"), ("NSFP's rate, 0.008", "tune/nsfp_rate"),
            ("patience 400, any improvement", "tune/patient"),
            ("the job's fit, held-out seeds", "held_out/baseline"),
            ("NSFP's rate, held-out seeds", "held_out/nsfp_rate"))


def _ns_pair(summary, key, fmt="{:.3f}"):
    """"0-5 band / 10-20 band" of one summary figure."""
    return Calc("{}", lambda a, b: f"{fmt.format(a)} / {fmt.format(b)}",
                (V(_NS, f"{summary}/0-5/{key}"), V(_NS, f"{summary}/10-20/{key}")))


NSFP_SPEED_BANDS_TABLE = Table(
    _LF, Quote(_LF, "`lab/tools/benchmark_nsfp_speed.py`, synthetic pairs of {} points a sweep (the `{}` lidars), "
                    "errors in m, the mean over seeds {} (tuning) and {} (held out), {}:",
               (V(_NS, "pairs/points_per_sweep", "{:,}"), V(_NS, "pairs/sensor"),
                Calc("{}", lambda s: " and ".join(map(str, s)), (V(_NS, "pairs/tune_seeds"),)),
                Calc("{}", lambda s: " and ".join(map(str, s)), (V(_NS, "pairs/held_out_seeds"),)),
                on_cpu(_NS, "machine"))),
    ("fit", "moving vehicles, 0-5 / 10-20 m/s", "10-20 over 0-5", "static foreground", "background", "three-way",
     "Adam steps"), "lrrrrrr",
    tuple((label, _ns_pair(summary, "moving_vehicle_epe_m"), V(_NS, f"{summary}/fast_over_slow", "{:.2f}x"),
           _ns_pair(summary, "fg_static_epe_m"), _ns_pair(summary, "bg_static_epe_m"),
           _ns_pair(summary, "mean_epe_m"), _ns_pair(summary, "iterations", "{:.0f}"))
          for label, summary in _NS_ROWS))
NSFP_SPEED_QUOTES = (
    Quote(_LF, "on every 10-20 m/s pair the objective is lowest at {} to {} times the true motion, and at the true "
               "motion it is {} to {} of its value at zero motion",
          (Calc("{:.2f}", lambda p: min(v["argmin_scale"] for k, v in p.items() if k.startswith("10-20/")),
                (V(_NS, "chamfer_profile"),)),
           Calc("{:.2f}", lambda p: max(v["argmin_scale"] for k, v in p.items() if k.startswith("10-20/")),
                (V(_NS, "chamfer_profile"),)),
           Calc("{:.0%}", lambda p: min(v["at_truth_over_at_zero"] for k, v in p.items() if k.startswith("10-20/")),
                (V(_NS, "chamfer_profile"),)),
           Calc("{:.0%}", lambda p: max(v["at_truth_over_at_zero"] for k, v in p.items() if k.startswith("10-20/")),
                (V(_NS, "chamfer_profile"),)))),
    Quote(_LF, "NSFP's rate scores {} m three-way on it, better on the static points, but moving foreground {} m and "
               "bucketed normalized dynamic EPE {}, above the job's bar of {} ({} Adam steps)",
          (V(_NS, "real_pair/nsfp_rate/mean_epe_m", "{:.3f}"), V(_NS, "real_pair/nsfp_rate/fg_dynamic_epe_m", "{:.3f}"),
           V(_NS, "real_pair/nsfp_rate/bucketed_mean_dynamic_norm_epe", "{:.3f}"),
           V(_NSFP, (_AV2S, "bar_at_most", "bucketed/mean_dynamic_norm_epe")), V(_NS, "real_pair/nsfp_rate/iterations"))),
    Quote(_LF, "On the real pair in `data/` the job's fit scores {} m three-way, moving foreground {} m, background "
               "{} m, bucketed normalized dynamic EPE {} ({} Adam steps, {} s on {}).",
          (V(_NS, "real_pair/baseline/mean_epe_m", "{:.3f}"), V(_NS, "real_pair/baseline/fg_dynamic_epe_m", "{:.3f}"),
           V(_NS, "real_pair/baseline/bg_static_epe_m", "{:.3f}"),
           V(_NS, "real_pair/baseline/bucketed_mean_dynamic_norm_epe", "{:.3f}"), V(_NS, "real_pair/baseline/iterations"),
           V(_NS, "real_pair/baseline/fit_s", "{:.0f}"), on_cpu(_NS, "machine"))),
)

# -- distillation (benchmark_distillation.py)
_DI = "distillation_synthetic.json"


def _verdict(key, who, fmt="{:.2f}"):
    return V(_DI, f"verdict/{key}/{who}", fmt)


DISTILLATION_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_distillation.py`, synthetic WOD at lidar scale {} ({} training and {} held-out "
                "segments), `{}`, {} training steps, NSFP capped at {} steps; error on the held-out pairs against "
                "their human labels, {}, family/model {} ({} cores):",
             (V(_DI, "options/lidar_scale"), V(_DI, "options/train_segments"), V(_DI, "options/eval_segments"),
              V(_DI, "options/config"), V(_DI, "options/steps"), V(_DI, "options/nsfp/max_iterations"),
              V(_DI, "cpu/model_name"), V(_DI, "cpu/family_model"), V(_DI, "machine/cpus"))),
    ("", "moving (m/s)", "stationary (m/s)", "foreground dynamic EPE (m)"), "lrrr",
    (("FastFlow3D, human labels", _verdict("all_moving_mean_l2_mps", "human"),
      _verdict("all_stationary_mean_l2_mps", "human"), _verdict("fg_dynamic_epe_m", "human", "{:.3f}")),
     ("FastFlow3D, NSFP pseudo-labels", _verdict("all_moving_mean_l2_mps", "pseudo"),
      _verdict("all_stationary_mean_l2_mps", "pseudo"), _verdict("fg_dynamic_epe_m", "pseudo", "{:.3f}")),
     ("zero flow", _verdict("all_moving_mean_l2_mps", "zero_flow"),
      _verdict("all_stationary_mean_l2_mps", "zero_flow"), _verdict("fg_dynamic_epe_m", "zero_flow", "{:.3f}")),
     ("the pseudo-labels themselves (training pairs)",
      V(_DI, ("pseudo_labels", "metrics", "all/moving/mean_l2_mps"), "{:.2f}"),
      V(_DI, ("pseudo_labels", "metrics", "all/stationary/mean_l2_mps"), "{:.2f}"), "")))

# -- faults (soak_train.py)
_SOAK = "soak_train.json"
_SOAK_KINDS = (("plain", "SIGKILL trainer"), ("plain", "SIGTERM trainer"), ("service", "SIGKILL dispatcher"),
               ("service", "SIGKILL input"), ("service", "SIGKILL trainer"), ("service", "SIGTERM dispatcher"),
               ("service", "SIGTERM input"), ("service", "SIGTERM trainer"))


def _soak(mode, kind, key, fmt="{}"):
    return V(_SOAK, f"{mode}/summary/by_kind/{kind}/{key}", fmt)


SOAK_TABLE = Table(
    B, Quote(B, "`lab/tools/soak_train.py`, two trainers on loopback (tiny model), {}; {} faults over {} "
                "steps without the service, {} over {} with it:",
             (on_cpu(_SOAK, "plain/cpu"), V(_SOAK, "plain/faults_injected"), V(_SOAK, "plain/final_step"),
              V(_SOAK, "service/faults_injected"), V(_SOAK, "service/final_step"))),
    ("run", "fault", "count", "detected, median / max", "resumed, median / max", "steps lost, max"), "llrrrr",
    tuple(("trainers alone" if mode == "plain" else "with the tf.data service", kind, _soak(mode, kind, "count"),
           Calc("{}", lambda a, b: f"{a:.1f} / {b:.1f} s",
                (_soak(mode, kind, "detect_s_median"), _soak(mode, kind, "detect_s_max"))),
           Calc("{}", lambda a, b: f"{a:.0f} / {b:.0f} s",
                (_soak(mode, kind, "resume_s_median"), _soak(mode, kind, "resume_s_max"))),
           _soak(mode, kind, "steps_lost_max")) for mode, kind in _SOAK_KINDS))

# -- TensorFlow's oneDNN operations on an AVX2-only CPU (benchmark_onednn.py)
_DNN = "cpu_onednn_avx2.json"


def _dnn(cap, onednn, key):
    return _ms(_DNN, f"summary/{cap}_onednn_{onednn}/{key}")


ONEDNN_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_onednn.py`, `{}`, {} points, batch 1, medians over {} rounds, {} ({} cores):",
             (V(_DNN, "config"), V(_DNN, "points", "{:,}"), V(_DNN, "rounds"), V(_DNN, "cpu/model_name"),
              V(_DNN, "cpu/cpu_count"))),
    ("ISA", "oneDNN", "training step", "forward"), "llrr",
    tuple((label, onednn_label, _dnn(cap, onednn, "train_step_ms"), _dnn(cap, onednn, "forward_ms"))
          for cap, label in (("avx2", "capped to AVX2 (as on AMD Zen 3)"), ("none", "the CPU's own"))
          for onednn, onednn_label in (("0", "off"), ("1", "on"))))

# -- heads and losses (benchmark_heads.py), in docs/training.md
_HB = "heads_synthetic.json"
_HB_SEED1 = "heads_synthetic_seed1.json"  # the same run with train.seed=1
_HB_DOC = "docs/training.md"
_HB_VARIANTS = (("paper_l2", "paper head + L2"), ("gru_l2", "GRU head + L2"), ("gru_deflow", "GRU head + DeFlow loss"),
                ("gru_deltaflow", "GRU head + DeltaFlow loss"),
                ("gru2_deltaflow", "GRU (2 iterations) + DeltaFlow loss"),
                ("gru_deflow_augment", "GRU + DeFlow + augmentation"),
                ("zero_flow", "zero flow"))
_HB_COLUMNS = ("moving_mps", "stationary_mps", "fg_dynamic_epe_m", "three_way_mean_epe_m", "bucketed_dynamic_norm_epe")


def _head_cell(source_file, fmt, variant, column):
    """A figure of the heads benchmark's headline, 3 decimals; n/a where the evaluation had no such points."""
    return Calc("{}", lambda v: "n/a" if v is None else f"{v:.3f}",
                (V(source_file, f"formats/{fmt}/headline/{variant}/{column}"),))


def _heads_table(source_file):
    return Table(
        _HB_DOC, Quote(_HB_DOC, f"`benchmarks/{source_file}`: {{}} training steps a variant, seed {{}}, `{{}}`, "
                                "synthetic data in the formats {} ({} training and {} held-out WOD segments or AV2 "
                                "logs of {} frames, WOD lidar scale {}); error on the held-out pairs, {} ({} cores):",
                       (V(source_file, "options/steps"), V(source_file, "options/seed"),
                        V(source_file, "options/config"),
                        Calc("{}", lambda f: ", ".join(f), (V(source_file, "options/formats"),)),
                        V(source_file, "options/train_segments"), V(source_file, "options/eval_segments"),
                        V(source_file, "options/frames_per_segment"), V(source_file, "options/lidar_scale"),
                        V(source_file, "cpu/model_name"), V(source_file, "cpu/cpu_count"))),
        ("data", "variant", "moving (m/s)", "stationary (m/s)", "fg dynamic EPE (m)", "three-way mean EPE (m)",
         "bucketed dynamic (normalized)"), "llrrrrr",
        tuple((fmt, label, *(_head_cell(source_file, fmt, variant, c) for c in _HB_COLUMNS))
              for fmt in lookup(source(source_file), "options/formats") for variant, label in _HB_VARIANTS))


HEADS_TABLE = _heads_table(_HB)
HEADS_SEED1_TABLE = _heads_table(_HB_SEED1)

# -- several sweeps: accuracy over seeds (benchmark_sweeps.py) and cost (benchmark_sweeps_cost.py)
_SW, _SC = "sweeps_synthetic.json", "sweeps_cost_cpu.json"
_SW_VARIANTS = (("paper_pair", "paper model, 2 sweeps"), ("gru_deltaflow_pair", "GRU + DeltaFlow loss, 2 sweeps"),
                ("stack_3", "GRU + DeltaFlow loss, stack of 3"), ("delta_3", "GRU + DeltaFlow loss, delta of 3"),
                ("delta_5", "GRU + DeltaFlow loss, delta of 5"))
_SW_COLUMNS = ("moving_mps", "stationary_mps", "three_way_mean_epe_m", "bucketed_dynamic_norm_epe")
_SC_VARIANTS = (("pair_2", "pair, 2 sweeps"), ("stack_3", "stack, 3 sweeps"), ("delta_3", "delta, 3 sweeps"),
                ("delta_5", "delta, 5 sweeps"))


def _spread_cell(path):
    return Calc("{}", lambda s: "n/a" if s["mean"] is None else f"{s['mean']:.3f} ± {s['std']:.3f}", (V(_SW, path),))


SWEEPS_TABLE = Table(
    B, Quote(B, "`benchmarks/sweeps_synthetic.json`: {} training steps a run, seeds {}, `{}`, {} training and {} "
                "held-out synthetic WOD segments, and as many Argoverse 2 logs, of {} sweeps each (WOD at lidar scale "
                "{}, AV2 at {} points a sweep); error on the held-out pairs (AV2: the 2024 challenge's protocol), "
                "mean ± sample standard deviation over the seeds, {} ({} cores):",
             (V(_SW, "options/steps"), Calc("{}", lambda s: ", ".join(map(str, s)), (V(_SW, "options/seeds"),)),
              V(_SW, "options/config"), V(_SW, "options/train_segments"), V(_SW, "options/eval_segments"),
              V(_SW, "options/frames_per_segment"), V(_SW, "options/lidar_scale"),
              V(_SW, "options/av2_points_per_sweep", "{:,}"), V(_SW, "cpu/model_name"), V(_SW, "cpu/cpu_count"))),
    ("data", "model", "moving (m/s)", "stationary (m/s)", "three-way mean EPE (m)", "bucketed dynamic (normalized)"),
    "llrrrr",
    tuple((fmt, label, *(_spread_cell(f"formats/{fmt}/{part}/{c}") for c in _SW_COLUMNS))
          for fmt in lookup(source(_SW), "formats")
          for part, label in [(f"per_variant/{v}", label) for v, label in _SW_VARIANTS] + [("zero_flow", "zero flow")]))


_SEPARATIONS = (("moving_mps", "moving error", " m/s"),
                ("bucketed_dynamic_norm_epe", "bucketed dynamic error (normalized, the Argoverse 2 board's figure)", ""))


def _separation(which: str, fmt: str, figure: str, unit: str) -> Calc:
    """The sentence part of one separation: "D apart against a seed range of R (apart | not apart)"."""
    def text(s):
        return (f"{s['difference']:.3f}{unit} apart against a seed range of {s['largest_range']:.3f}{unit} "
                f"({'apart' if s['apart'] else 'not apart'})")
    return Calc("{}", text, (V(_SW, f"formats/{fmt}/separations/{figure}/{which}"),))


# The instrument, a planted defect against the corrected delta: on the realistic profile's logs and the plain ones.
_SP, _SP_PLAIN = "sweeps_planted_av2.json", "sweeps_planted_av2_plain.json"
_SP_NAMES = {"paper_pair": "paper model, 2 sweeps", "gru_deltaflow_pair": "GRU + DeltaFlow loss, 2 sweeps",
             "stack_3": "GRU + DeltaFlow loss, stack of 3", "delta_3": "DeltaFlow head and loss, delta of 3",
             "delta_5": "DeltaFlow head and loss, delta of 5",
             "delta_5_reversed": "planted defect: delta of 5 reversed",
             "delta_5_no_ground": "DeltaFlow head and loss, delta of 5, ground dropped", "zero_flow": "zero flow"}


def _planted_cell(file, path):
    return Calc("{}", lambda s: "n/a" if s["mean"] is None else f"{s['mean']:.3f} ± {s['std']:.3f}",
                (V(file, path),))


def _planted_rows(file):
    """Per format, the full part's variants and zero flow, then the filled-history part's (where the run scored one):
    the rows `lab.training.sweeps_benchmark.table` writes."""
    result = source(file)
    rows = []
    for fmt, part in lookup(result, "formats").items():
        for label, prefix in ((fmt, f"formats/{fmt}"), (f"{fmt}, filled history", f"formats/{fmt}/filled")):
            if prefix.endswith("/filled") and "filled" not in part:
                continue
            summary = lookup(result, prefix)
            rows += [(label, _SP_NAMES[v], *(_planted_cell(file, f"{prefix}/per_variant/{v}/{c}") for c in _SW_COLUMNS))
                     for v in summary["per_variant"]]
            rows.append((label, _SP_NAMES["zero_flow"],
                         *(_planted_cell(file, f"{prefix}/zero_flow/{c}") for c in _SW_COLUMNS)))
    return tuple(rows)


def _planted_table(file):
    return Table(
        B, Quote(B, f"`benchmarks/{file}` (`{{}}`): {{}} training steps a run, seeds {{}}, `{{}}`, {{}} training and "
                    "{} held-out synthetic logs of {} sweeps each in the formats {} ({} points a sweep for Argoverse "
                    "2; the generator's realistic profile: {}); error on the held-out t0 sweeps (Argoverse 2: the "
                    "2024 challenge's protocol), mean ± sample standard deviation over the seeds, {} ({} cores):",
                 (V(file, "command"), V(file, "options/steps"),
                  Calc("{}", lambda s: ", ".join(map(str, s)), (V(file, "options/seeds"),)),
                  V(file, "options/config"), V(file, "options/train_segments"), V(file, "options/eval_segments"),
                  V(file, "options/frames_per_segment"),
                  Calc("{}", lambda f: ", ".join(f), (V(file, "options/formats"),)),
                  V(file, "options/av2_points_per_sweep", "{:,}"),
                  Calc("{}", lambda r: "yes" if r else "no", (V(file, "options/realistic"),)),
                  V(file, "cpu/model_name"), V(file, "cpu/cpu_count"))),
        ("data", "model", "moving (m/s)", "stationary (m/s)", "three-way mean EPE (m)", "bucketed dynamic (normalized)"),
        "llrrrr", _planted_rows(file))


PLANTED_TABLE, PLANTED_PLAIN_TABLE = _planted_table(_SP), _planted_table(_SP_PLAIN)


def _instrument(file: str, fmt: str, figure: str, unit: str) -> Calc:
    """The sentence part of the planted defect against delta of 5 on one figure."""
    def text(s):
        verdict = "caught" if s["caught"] else "not caught"
        return (f"{s['difference']:.3f}{unit} apart against a seed range of {s['largest_range']:.3f}{unit}, the "
                f"planted defect {'worse' if s['planted_worse'] else 'better'} ({verdict})")
    return Calc("{}", text, (V(file, f"formats/{fmt}/instrument/{figure}"),))


SWEEPS_COST_TABLE = Table(
    B, Quote(B, "`benchmarks/sweeps_cost_cpu.json` (`{}`), paper config with the paper head, {} points a sweep, "
                "medians, each variant in its own process, {} ({} cores):",
             (V(_SC, "command"), V(_SC, "variants/pair_2/points_per_sweep", "{:,}"), V(_SC, "cpu/model_name"),
              V(_SC, "cpu/cpu_count"))),
    ("sweeps", "parameters", "forward", "over the pair's", "training step", "over the pair's", "peak RSS",
     "portable XLA forward"), "lrrrrrrr",
    tuple((label, V(_SC, f"variants/{v}/params", "{:,}"), _ms(_SC, f"variants/{v}/forward/median_ms"),
           V(_SC, f"ratios_to_pair/{v}/forward", "{:.2f}x"), _ms(_SC, f"variants/{v}/train_step/median_ms"),
           V(_SC, f"ratios_to_pair/{v}/train_step", "{:.2f}x"), V(_SC, f"variants/{v}/peak_rss_gb", "{:.2f} GB"),
           Calc("{:,.0f} kB", lambda sizes: sum(sizes.values()) / 1e3, (V(_SC, f"variants/{v}/xla_forward_bytes"),)))
          for v, label in _SC_VARIANTS))

TABLES = (LATENCY_TABLE, BF16_TABLE, MEMORY_TABLE, ONNX_TABLE, GPU_FORWARD_TABLE, GPU_TRAIN_TABLE, INPUT_TABLE,
          AV2_INPUT_TABLE, TRAINING_INPUT_TABLE, SIZING_TABLE, NSFP_SPEED_TABLE, NSFP_QUALITY_TABLE, DISTILLATION_TABLE,
          SOAK_TABLE, ONEDNN_TABLE, HEADS_TABLE, HEADS_SEED1_TABLE, SWEEPS_TABLE, SWEEPS_COST_TABLE,
          PLANTED_TABLE, PLANTED_PLAIN_TABLE, NSFP_SPEED_BANDS_TABLE)

_1M = "latency_cpu_1m.json"
_AMD_DIFF = "summary/flow_difference_bfloat16_vs_float32_mps"
_AMX_DEMO = "demo/relative_difference_vs_float32"
_NX = "nsfp_xla_cpu.json"
_AN = "annotation_cpu.json"


def _mb(figure) -> Calc:
    return Calc("{:.1f}", lambda b: b / 1e6, (figure,))


def _gpu_ref(precision, fmt):
    return V(_GPU, f"latency[points=32000,precision={precision}]/reference/max_abs_flow_diff_mps", fmt)


_SUB = "av2_submission.json"

QUOTES = tuple(
    Quote(B, f"{fmt.upper()}, {label}: zero flow and the paper's model are {{}}; the best of the other variants, "
             "`{}`, and the paper's model are {}.",
          (_separation("zero_flow_vs_paper_pair", fmt, figure, unit),
           V(_SW, f"formats/{fmt}/separations/{figure}/best_variant"),
           _separation("paper_pair_vs_best_variant", fmt, figure, unit)))
    for fmt in lookup(source(_SW), "formats") for figure, label, unit in _SEPARATIONS) + (
    *(Quote(B, f"{fmt.upper()}, {label}: the planted defect and `delta` of 5 are {{}}.",
            (_instrument(file, fmt, figure, unit),))
      for file in (_SP, _SP_PLAIN) for fmt in lookup(source(file), "formats") for figure, label, unit in _SEPARATIONS),
    Quote(B, "The GRU variants train with DeltaFlow's gradient clip, `{}`, and a lower rate than the paper model's, "
             "`{}`: at the config's rate, on the benchmark's batch, their loss grew without bound",
          tuple(Calc("{}", lambda sets, key=key: next(s for s in sets if s.startswith(key)),
                     (V(_SW, "options/variants/delta_5/set"),))
                for key in ("train.grad_clip_norm=", "train.learning_rate="))),
    Quote(B, "`delta` on 5 sweeps costs {} the pair's forward (the target: at most {}x)",
          (V(_SC, "delta_5_forward_bar/measured", "{:.2f}x"), V(_SC, "delta_5_forward_bar/target_at_most"))),
    Quote("docs/training.md", "{} for the pair, {} for `stack` of 3 and {} for `delta`, whatever the number of sweeps",
          (V(_SC, "variants/pair_2/params", "{:,}"), V(_SC, "variants/stack_3/params", "{:,}"),
           V(_SC, "variants/delta_5/params", "{:,}"))),
    Quote("docs/datasets.md", "On the sample log's first sweep ({} points, `benchmarks/av2_submission.json`), "
                              "av2-api's rule keeps {} points with Argoverse's own ground labels and {} with the "
                              "records' ground ({} point is ground in one and not the other), and the protocol's 35 m "
                              "mask (`metrics_av2.eval_mask`) keeps {}:",
          (V(_SUB, "first_sweep_points", "{:,}"), V(_SUB, "rows_first_sweep/av2_api_rule/labels_ground", "{:,}"),
           V(_SUB, "rows_first_sweep/av2_api_rule/records_ground", "{:,}"),
           V(_SUB, "ground_points_records_vs_labels_differ"),
           V(_SUB, "rows_first_sweep/project_35m/records_ground", "{:,}"))),
    Quote(B, "oneDNN makes the training step {} faster than Eigen's kernels",
          (V(_DNN, "summary/avx2_onednn_speedup/train_step_ms", "{:.1f}x"),)),
    Quote("README.md", "the model exactly as the paper's architecture table ({} parameters)",
          (V(_LAT, "params", "{:,}"),)),
    Quote(B, "Peak resident memory of a process that runs the forward on {} points, one compile mode per process "
             "(`benchmarks/latency_cpu_1m.json`, {}): {} GB in `auto`, {} GB in `xla`.",
          (V(_1M, "latency/1000000/auto/padded_points", "{:,}"), on_cpu(_1M),
           V(_1M, "memory_single_mode_runs/auto/1000000/peak_rss_gb", "{:.2f}"),
           V(_1M, "memory_single_mode_runs/xla/1000000/peak_rss_gb", "{:.2f}"))),
    Quote(B, "On random weights of the paper config (`benchmarks/bf16_cpu_amd.json`, {}), bfloat16 moves the flow by "
             "at most {} m/s at 32,000 points (mean {} of the mean flow) and {} m/s at 1,000,000 points (mean {}).",
          (V(_AMD, "cpu/model_name"), V(_AMD, f"{_AMD_DIFF}/32000/max", "{:.2f}"),
           V(_AMD, f"{_AMD_DIFF}/32000/mean_over_mean_flow_norm", "{:.2%}"),
           V(_AMD, f"{_AMD_DIFF}/1000000/max", "{:.1f}"),
           V(_AMD, f"{_AMD_DIFF}/1000000/mean_over_mean_flow_norm", "{:.2%}"))),
    Quote(B, "The demo's model trained {} steps in bfloat16 (`benchmarks/bf16_cpu_amx.json`, {} with amx_bf16) differs "
             "from the float32 model in its error by {} on moving points and {} on stationary ones (one seed each: "
             "training noise); float32 weights run in bfloat16 change the error on moving points by {}.",
          (V(_AMX, "demo/train_steps"), V(_AMX, "cpu/model_name"),
           V(_AMX, (*_AMX_DEMO.split("/"), "trained_bfloat16", "all/moving/mean_l2_mps"), "{:+.1%}"),
           V(_AMX, (*_AMX_DEMO.split("/"), "trained_bfloat16", "all/stationary/mean_l2_mps"), "{:+.1%}"),
           V(_AMX, (*_AMX_DEMO.split("/"), "float32_weights_bfloat16_inference", "all/moving/mean_l2_mps"),
             "{:+.2%}"))),
    Quote(B, "Against TensorFlow on the export machine (CPU, float32), on the same inputs at 32,000 points: float32 "
             "flow within {} m/s, tf32 within {} m/s, bfloat16 within {} m/s (random weights), validity identical.",
          (_gpu_ref("float32", "{:.1e}"), _gpu_ref("tf32", "{:.3f}"), _gpu_ref("bfloat16", "{:.2f}"))),
    Quote(B, "Disk per pair at WOD's density: {} MB exact, {} MB compact, against {} MB per WOD frame record; for "
             "WOD's training split {} TB exact, {} TB compact. Writing runs at {} pairs/s per core.",
          (_mb(V(_IN, "densities/wod/sizes/exact_bytes_per_pair")),
           _mb(V(_IN, "densities/wod/sizes/compact_bytes_per_pair")),
           _mb(V(_IN, "densities/wod/sizes/frame_record_bytes")),
           V(_IN, "densities/wod/sizes/exact_wod_train_split_tb", "{:.2f}"),
           V(_IN, "densities/wod/sizes/compact_wod_train_split_tb", "{:.2f}"),
           V(_IN, "densities/wod/sizes/exact_write_pairs_per_s", "{:.1f}"))),
    Quote(B, "Argoverse 2 records take {} MB a pair exact and {} MB compact.",
          (_mb(V(_IN, "av2/runs/1/write_exact/bytes_per_pair")),
           _mb(V(_IN, "av2/runs/1/write_compact/bytes_per_pair")))),
    Quote(B, "the input is {} times faster than the step",
          (V(_TR, "input_headroom", "{:.0f}"),)),
    Quote(B, "Through the exported float32 program a step takes {} s against {} s in TensorFlow, a grid build {} s "
             "against {} s per cloud ({} points, the pseudo-label job's fit; `benchmarks/nsfp_xla_cpu.json`, "
             "jax {} on {}).",
          (V(_NX, "jax_seconds_per_step", "{:.2f}"), V(_NX, "tf_seconds_per_step", "{:.2f}"),
           V(_NX, "jax_grid_s_one_cloud", "{:.1f}"), V(_NX, "tf_grid_s_one_cloud", "{:.1f}"),
           V(_NX, "points", "{:,}"), V(_NX, "exported_with/jax"), on_cpu(_NX))),
    Quote(B, "Bar met: {}. The two tools took {} s together; the fit stopped early after {} Adam steps, and {} of the "
             "scored points had no pseudo-label (they are scored as zero flow).",
          (Calc("{}", lambda met: "yes" if met else "no", (V(_NSFP, f"{_AV2S}/meets_bar"),)),
           V(_NSFP, f"{_AV2S}/wall_s_both_tools", "{:.0f}"), V(_NSFP, f"{_AV2S}/counts/nsfp_iterations"),
           V(_NSFP, f"{_AV2S}/evaluated_points_without_pseudo_label", "{:,}"))),
    Quote(B, "At those {} steps a pair of the benchmark cloud costs {} s with the distance transform and {} s with "
             "exact nearest neighbours; at the cap of {} steps, {} s and {} s.",
          (V(_NSFP, f"{_AV2S}/counts/nsfp_iterations"),
           V(_NSFP, "seconds_per_pair/distance_transform/av2_sample_steps", "{:,.0f}"),
           V(_NSFP, "seconds_per_pair/exact_nearest_neighbours/av2_sample_steps", "{:,.0f}"),
           V(_NSFP, "options/max_iterations", "{:,}"),
           V(_NSFP, "seconds_per_pair/distance_transform/max_iterations", "{:,.0f}"),
           V(_NSFP, "seconds_per_pair/exact_nearest_neighbours/max_iterations", "{:,.0f}"))),
    Quote(B, "Pseudo-label training's error on moving points is {}x zero flow's and {}x the human-labelled model's",
          (V(_DI, "verdict/pseudo_over_zero_flow_moving", "{:.2f}"),
           V(_DI, "verdict/pseudo_over_human_moving", "{:.2f}"))),
    Quote(B, "Trainers alone: {} unexpected outcomes, {} hangs, {} lost checkpoints; the final weights equal an "
             "uninterrupted run's bit for bit ({} variables compared). With the service: {} unexpected outcomes, {} "
             "hangs, {} lost checkpoints; the mean loss of the last {} steps is {}x the uninterrupted run's (batches "
             "arrive in another order, so weights are not compared).",
          (V(_SOAK, "plain/summary/not_as_expected"), V(_SOAK, "plain/summary/hangs"),
           V(_SOAK, "plain/summary/lost_checkpoints"), V(_SOAK, "plain/variables_compared"),
           V(_SOAK, "service/summary/not_as_expected"), V(_SOAK, "service/summary/hangs"),
           V(_SOAK, "service/summary/lost_checkpoints"),
           V(_SOAK, "service/loss_window_steps"), V(_SOAK, "service/loss_ratio", "{:.2f}"))),
    Quote(B, "(`benchmarks/annotation_cpu.json`, a synthetic segment of {} frames, {} points a frame, {}): "
             "the first segment of a process takes {} s to its first frame (the decoder is traced once per process), "
             "then {} frames/s; later segments run at {} frames/s.",
          (V(_AN, "frames"), V(_AN, "points_per_frame", "{:,.0f}"), on_cpu(_AN),
           V(_AN, "cold_first_frame_seconds", "{:.1f}"), V(_AN, "cold_steady_fps", "{:.1f}"),
           V(_AN, "warm_steady_fps", "{:.1f}"))),
    *NSFP_SPEED_QUOTES,
)


# -- the training step and the forward on an AVX2-only CPU, before and after (benchmark_cpu_step.py)
_CS = "cpu_step_avx2.json"
_CS_MODES = ("auto", "hybrid", "xla", "none")


def _cs(path, fmt):
    return V(_CS, ("summary",) + tuple(path), fmt)


def _cs_na(path, fmt):
    """A figure that a mode may lack (BatchNorm inside an XLA program, a failed variant): "n/a"."""
    def text(data):
        try:
            value = lookup(data, ("summary",) + tuple(path))
        except (KeyError, TypeError):
            value = None
        return "n/a" if value is None else fmt.format(value)
    return Calc("{}", text, (V(_CS, ()),))


_CS_WHERE = Quote(B, "{} ({} cores), oneDNN and XLA capped to AVX2 (`ff3d_tf.cpu.EMULATIONS`, `zen3`: as on an AMD "
                     "Zen 3)", (V(_CS, "cpu/model_name"), V(_CS, "cpu/cpu_count")))
CPU_STEP_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_cpu_step.py`, paper config, {} points, batch 1, median of {} training steps "
                "after {} warm-up steps (wall time, and CPU time of all threads), peak = the process's peak resident "
                "memory; {}:", (V(_CS, "train_points", "{:,}"), V(_CS, "steps"), V(_CS, "warmup"), _CS_WHERE)),
    ("`model.compile`", "before: runs", "before: step", "before: CPU", "before: peak", "after: runs", "after: step",
     "after: CPU", "after: peak"), "llrrrlrrr",
    tuple((f"`{m}`", *(cell for setting in ("before", "after") for cell in (
        _cs((f"train/{m}", setting, "mode"), "{}"),
        _cs_na((f"train/{m}", setting, "step_median_ms"), "{:,.0f} ms"),
        _cs_na((f"train/{m}", setting, "step_cpu_median_ms"), "{:,.0f} ms"),
        _cs_na((f"train/{m}", setting, "peak_rss_gb"), "{:.2f} GB")))) for m in _CS_MODES))
_CS_STAGES = (("point stages (rows A-B, W-Z), forward", "point_forward_ms"),
              ("point stages, backward", "point_backward_ms"), ("convolutions (rows C-V), forward", "conv_forward_ms"),
              ("convolutions, backward", "conv_backward_ms"),
              ("of the convolutions: BatchNorm kernels", "batchnorm_ms"), ("optimizer (Adam)", "optimizer_ms"),
              ("loss", "loss_ms"), ("rest: copies between kernels and XLA programs, launches", "rest_ms"))
CPU_STAGES_TABLE = Table(
    B, Quote(B, "The parts of the step in `auto` (the modes of the table above), each timed alone in the same "
                "processes after the steps, medians of {} calls:", (V(_CS, "variants/train/auto/after/stage_runs"),)),
    ("part", "before", "after"), "lrr",
    tuple((label, _cs_na(("train/auto", "before", "stages", key), "{:,.0f} ms"),
           _cs_na(("train/auto", "after", "stages", key), "{:,.0f} ms")) for label, key in _CS_STAGES))
CPU_FORWARD_TABLE = Table(
    B, Quote(B, "The forward, median of {} calls after {} warm-up calls, both point counts in one process; {}:",
             (V(_CS, "runs"), V(_CS, "warmup"), _CS_WHERE)),
    ("`model.compile`", "before: 32,000 points", "before: 1,000,000 points", "before: ratio", "after: runs",
     "after: 32,000 points", "after: 1,000,000 points", "after: ratio"), "lrrrlrrr",
    tuple((f"`{m}`", _cs_na((f"forward/{m}", "before", "median_ms", "32000"), "{:,.0f} ms"),
           _cs_na((f"forward/{m}", "before", "median_ms", "1000000"), "{:,.0f} ms"),
           _cs_na((f"forward/{m}", "before", "t1m_over_t32k"), "{:.2f}"), _cs((f"forward/{m}", "after", "mode"), "{}"),
           _cs_na((f"forward/{m}", "after", "median_ms", "32000"), "{:,.0f} ms"),
           _cs_na((f"forward/{m}", "after", "median_ms", "1000000"), "{:,.0f} ms"),
           _cs_na((f"forward/{m}", "after", "t1m_over_t32k"), "{:.2f}")) for m in _CS_MODES))


def _target(what, figure, goal, fmt, at_least):
    """(what, the figure, the target, whether it is met)."""
    met = Calc("{}", lambda p, g: "yes" if (p >= g if at_least else p <= g) else "no", (figure, goal))
    return what, figure, Calc(fmt, lambda g: g, (goal,)), met


def _speed_targets(file, what, key):
    """The target rows of a speed-up `key` in `file`'s projection: by wall time, then by CPU time."""
    goal = V(file, f"targets/{key}")
    return (_target(what, V(file, f"projection_zen3/{key}", "{:.2f}x"), goal, "{:.2f}x", True),
            _target("the same by CPU time", V(file, f"projection_zen3/{key}_by_cpu_time", "{:.2f}x"), goal, "{:.2f}x",
                    True))


def _targets_table(file):
    """The issue's targets against `file`'s projection onto its Zen 3 figures (`projection_zen3`)."""
    return Table(
        B, Quote(B, "The issue's figures on {} (PyTorch FastFlow3D: {} ms a training step, {} GB peak, {} ms and "
                    "{} ms a forward at 32,000 and 1,000,000 points; ff3d_tf before: {} ms, {} GB, {} ms and {} ms), "
                    "scaled by the after / before ratios of `auto` in `benchmarks/" + file + "` (by wall time, and "
                    "by CPU time where named); the forward's ratio of point counts is the run's own:",
                 (V(file, "peer/cpu"), V(file, "peer/peer/train_step_32000_ms", "{:,.0f}"),
                  V(file, "peer/peer/train_step_32000_peak_gb", "{:.2f}"),
                  V(file, "peer/peer/forward_32000_ms", "{:,.0f}"),
                  V(file, "peer/peer/forward_1000000_ms", "{:,.0f}"),
                  V(file, "peer/ff3d_tf_before/train_step_32000_ms", "{:,.0f}"),
                  V(file, "peer/ff3d_tf_before/train_step_32000_peak_gb", "{:.2f}"),
                  V(file, "peer/ff3d_tf_before/forward_32000_ms", "{:,.0f}"),
                  V(file, "peer/ff3d_tf_before/forward_1000000_ms", "{:,.0f}"))),
        ("figure", "ff3d_tf after", "target", "met"), "lrrl",
        (*_speed_targets(file, "training step, 32,000 points: speed-up over the peer",
                         "train_step_speedup_over_peer"),
         _target("training step, 32,000 points: peak memory",
                 V(file, "projection_zen3/train_step_32000_peak_gb", "{:.2f} GB"),
                 V(file, "targets/train_step_peak_gb"),
                 "{:.2f} GB", False),
         *_speed_targets(file, "forward, 32,000 points: speed-up over the peer", "forward_32000_speedup_over_peer"),
         *_speed_targets(file, "forward, 1,000,000 points: speed-up over the peer",
                         "forward_1000000_speedup_over_peer"),
         _target("forward: time at 1,000,000 points / time at 32,000 points",
                 V(file, ("summary", "forward/auto", "after", "t1m_over_t32k"), "{:.2f}"),
                 V(file, "targets/forward_1m_over_32k"), "{:.2f}", False)))
TABLES += (CPU_STEP_TABLE, CPU_STAGES_TABLE, CPU_FORWARD_TABLE)

# -- the training step's memory per start-up setting (benchmark_cpu_step.py --jobs train --settings ...): glibc's
# malloc arenas (after_default_arenas: without the start-up's limit) and the encoder recomputed (after_remat)
_STEP_SETTINGS = {"before": "before (TensorFlow's own start-up, `auto` = hybrid)",
                  "after": "after (the tools' start-up, `auto` per job)",
                  "after_remat": "after, `model.remat_encoder=true`",
                  "after_default_arenas": "after, glibc's own malloc arenas (no `MALLOC_ARENA_MAX`)",
                  "after_plain_convolutions": "after, the convolutions in their plain forms",
                  "after_huge_pages": "after, transparent huge pages (`GLIBC_TUNABLES=glibc.malloc.hugetlb=1`)"}


def _settings_table(file, settings, jobs="train"):
    """The training step of each of `settings` in `file`, measured and projected onto the issue's Zen 3 figures
    (`projection_zen3`: "after"'s at its top level, another setting's under its own key; "before" is the issue's)."""
    def projected(setting, key, fmt):
        if setting == "before":
            return V(file, ("peer", "ff3d_tf_before", key), fmt)
        return V(file, ("projection_zen3",) + (() if setting == "after" else (setting,)) + (key,), fmt)

    return Table(
        B, Quote(B, f"`lab/tools/benchmark_cpu_step.py --jobs {jobs} --modes auto --settings {','.join(settings)} "
                    f"--rounds {{}} --no_stages` (`benchmarks/{file}`), paper config, {{}} points, batch 1, the "
                    "middle over the rounds (`bench.middle`: the median; of two, the larger) of the median of {} steps after {} "
                    "warm-up steps; {} ({} cores), oneDNN and XLA "
                    "capped to AVX2 (`zen3`); projected = the issue's Zen 3 figures of ff3d_tf before scaled by this "
                    "run's ratios to its own \"before\":",
                 (V(file, "rounds"), V(file, "train_points", "{:,}"), V(file, "steps"), V(file, "warmup"),
                  V(file, "cpu/model_name"), V(file, "cpu/cpu_count"))),
        ("setting", "runs", "step", "CPU", "peak", "projected step", "projected: over the peer", "projected peak"),
        "llrrrrrr",
        tuple((_STEP_SETTINGS[setting], V(file, ("summary", "train/auto", setting, "mode")),
               V(file, ("summary", "train/auto", setting, "step_median_ms"), "{:,.0f} ms"),
               V(file, ("summary", "train/auto", setting, "step_cpu_median_ms"), "{:,.0f} ms"),
               V(file, ("summary", "train/auto", setting, "peak_rss_gb"), "{:.2f} GB"),
               projected(setting, "train_step_32000_ms", "{:,.0f} ms"),
               Calc("{:.2f}x", lambda peer, ms: peer / ms,
                    (V(file, "peer/peer/train_step_32000_ms"), projected(setting, "train_step_32000_ms", "{}"))),
               projected(setting, "train_step_32000_peak_gb", "{:.2f} GB"))
              for setting in settings))


MEMORY_TABLE = _settings_table("cpu_step_avx2_memory.json", ("before", "after", "after_default_arenas", "after_remat"))
_CF = "cpu_step_avx2_convolutions.json"
CONV_FORMS_TABLE = _settings_table(_CF, ("before", "after", "after_plain_convolutions"), jobs="train,forward")


def _forward_table(file, settings):
    """The forward of each of `settings` in `file` (a study run with `--jobs train,forward`)."""
    return Table(
        B, Quote(B, "The forward in the same run (`--jobs forward`, `auto`), the middle over the rounds of the median "
                    "of {} calls after {} warm-up calls, both point counts in one process:",
                 (V(file, "runs"), V(file, "warmup"))),
        ("setting", "runs", "32,000 points", "1,000,000 points", "ratio"), "llrrr",
        tuple((_STEP_SETTINGS[setting], V(file, ("summary", "forward/auto", setting, "mode")),
               V(file, ("summary", "forward/auto", setting, "median_ms", "32000"), "{:,.0f} ms"),
               V(file, ("summary", "forward/auto", setting, "median_ms", "1000000"), "{:,.0f} ms"),
               V(file, ("summary", "forward/auto", setting, "t1m_over_t32k"), "{:.2f}"))
              for setting in settings))


CONV_FORMS_FORWARD_TABLE = _forward_table(_CF, ("before", "after", "after_plain_convolutions"))


def _own_isa_table(file, settings):
    """The training step and the forward of each of `settings` in `file`, a study run with the CPU's own kernels."""
    return Table(
        B, Quote(B, f"`lab/tools/benchmark_cpu_step.py --cap none --jobs train,forward --modes auto --settings "
                    f"{','.join(settings)} --rounds {{}} --no_stages` (`benchmarks/{file}`), the same figures on {{}} "
                    "({} cores, family/model {}) with its own kernels (TensorFlow's oneDNN operations on, AVX-512):",
                 (V(file, "rounds"), V(file, "cpu/model_name"), V(file, "cpu/cpu_count"),
                  V(file, "cpu/family_model"))),
        ("setting", "runs", "training step", "peak", "forward, 32,000 points", "forward, 1,000,000 points"), "llrrrr",
        tuple((_STEP_SETTINGS[setting], V(file, ("summary", "train/auto", setting, "mode")),
               V(file, ("summary", "train/auto", setting, "step_median_ms"), "{:,.0f} ms"),
               V(file, ("summary", "train/auto", setting, "peak_rss_gb"), "{:.2f} GB"),
               V(file, ("summary", "forward/auto", setting, "median_ms", "32000"), "{:,.0f} ms"),
               V(file, ("summary", "forward/auto", setting, "median_ms", "1000000"), "{:,.0f} ms"))
              for setting in settings))


CONV_FORMS_OWN_ISA_TABLE = _own_isa_table("cpu_step_zen4_convolutions.json", ("after", "after_plain_convolutions"))
CONV_FORMS_REMAT_TABLE = _settings_table("cpu_step_avx2_convolutions_remat.json", ("before", "after", "after_remat"))
# Rows U5-V as one convolution (`ops.conv_chain_same`)
_CH = "cpu_step_avx2_chain.json"
CHAIN_TABLE = _settings_table(_CH, ("before", "after"), jobs="train,forward")
CHAIN_FORWARD_TABLE = _forward_table(_CH, ("before", "after"))


def _steps_peak(file):
    return Quote(
        B, "After the warm-up steps, the timed steps of \"after\" alone peak at {} (the peak above is the process's, "
           "from its start): {} projected onto the issue's Zen 3.",
        (V(file, ("summary", "train/auto", "after", "steps_peak_rss_gb"), "{:.2f} GB"),
         V(file, "projection_zen3/train_step_32000_steps_peak_gb", "{:.2f} GB")))


CHAIN_STEPS_PEAK = _steps_peak(_CH)
CHAIN_OWN_ISA_TABLE = _own_isa_table("cpu_step_zen4_chain.json", ("after",))
# The heap after the first step returned to the OS (`Trainer.step`), and transparent huge pages (not kept)
_PG = "cpu_step_avx2_pages.json"
PAGES_TABLE = _settings_table(_PG, ("before", "after", "after_huge_pages"), jobs="train,forward")
PAGES_FORWARD_TABLE = _forward_table(_PG, ("before", "after"))
PAGES_STEPS_PEAK = _steps_peak(_PG)
PAGES_FAULTS = Quote(
    B, "A training step's minor page faults (the middle over the rounds of each run's median step): {} with huge pages, "
       "{} without; the system's CPU time in the step (the kernel filling pages, mostly): {} and {}.",
    tuple(V(_PG, ("summary", "train/auto", setting, key), fmt) for key, fmt in
          (("step_minor_faults_median", "{:,.0f}"), ("step_sys_median_ms", "{:,.0f} ms"))
          for setting in ("after_huge_pages", "after")))
CPU_TARGETS_TABLE = _targets_table(_PG)
TABLES += (MEMORY_TABLE, CONV_FORMS_TABLE, CONV_FORMS_FORWARD_TABLE, CONV_FORMS_OWN_ISA_TABLE, CONV_FORMS_REMAT_TABLE,
           CHAIN_TABLE, CHAIN_FORWARD_TABLE, CHAIN_OWN_ISA_TABLE, PAGES_TABLE, PAGES_FORWARD_TABLE, CPU_TARGETS_TABLE)
QUOTES += (CHAIN_STEPS_PEAK, PAGES_STEPS_PEAK, PAGES_FAULTS)

# -- the training step on an AVX-512/AMX CPU (benchmark_cpu_step.py --cap none), against the issue's figures there
# (benchmarks/cpu_step_peer_amx.json); what the process holds (profile_memory.py on the same kind of CPU)
_AMX, _AMX_PEER = "cpu_step_amx.json", "cpu_step_peer_amx.json"
_AMX_SETTINGS = {"after": ("after (the tools' start-up: oneDNN on, its BFC pool)", "float32"),
                 "after_remat": ("after, `model.remat_encoder=true`", "float32"),
                 "after_no_pool": ("after, every tensor from malloc, two arenas (no pool)", "float32"),
                 "after_eigen": ("after, the AVX2 start-up (oneDNN off, two arenas)", "float32"),
                 "after_bfloat16": ("after, `model.mixed_precision=true` (what `auto` takes here)", "bfloat16"),
                 "after_remat_bfloat16": ("after, bfloat16 and `model.remat_encoder=true`", "bfloat16")}


def _amx(setting, key, fmt="{}"):
    return V(_AMX, ("summary", "train/auto", setting, key), fmt)


def _amx_projected(setting):
    """The issue's ff3d_tf step on this kind of CPU scaled by the run's ratio of `setting` to "after"."""
    return Calc("{:,.0f} ms", lambda issue, ms, after: issue * ms / after,
                (V(_AMX_PEER, "ff3d_tf_before/train_step_32000_ms"), _amx(setting, "step_median_ms"),
                 _amx("after", "step_median_ms")))


AMX_STEP_TABLE = Table(
    B, Quote(B, "`lab/tools/benchmark_cpu_step.py --cap none --jobs train --modes auto --settings {} --rounds {} "
                "--no_stages` (`benchmarks/" + _AMX + "`), paper config, {} points, batch 1, the middle over the "
                "rounds of the median of {} steps after {} warm-up steps; {}, family/model {} ({} cores, its own "
                "kernels); projected = the issue's ff3d_tf step on this kind of CPU ({} ms, float32, the start-up of "
                "\"after\") scaled by this run's ratio to its own \"after\"; the peer's step there: {} ms, {} GB:",
             (Calc("{}", lambda settings: ",".join(settings), (V(_AMX, "variants/train/auto"),)), V(_AMX, "rounds"),
              V(_AMX, "train_points", "{:,}"), V(_AMX, "steps"), V(_AMX, "warmup"), V(_AMX, "cpu/model_name"),
              V(_AMX, "cpu/family_model"), V(_AMX, "cpu/cpu_count"),
              V(_AMX_PEER, "ff3d_tf_before/train_step_32000_ms", "{:,.0f}"),
              V(_AMX_PEER, "peer/train_step_32000_ms", "{:,.0f}"), V(_AMX_PEER, "peer/train_step_32000_peak_gb"))),
    ("setting", "precision", "runs", "step", "CPU", "peak", "projected step", "projected: over the peer"),
    "llrrrrrr",
    tuple((what, precision, _amx(setting, "mode"), _amx(setting, "step_median_ms", "{:,.0f} ms"),
           _amx(setting, "step_cpu_median_ms", "{:,.0f} ms"), _amx(setting, "peak_rss_gb", "{:.2f} GB"),
           _amx_projected(setting),
           Calc("{:.2f}x", lambda peer, ms: peer / ms, (V(_AMX_PEER, "peer/train_step_32000_ms"),
                                                         _amx_projected(setting))))
          for setting, (what, precision) in _AMX_SETTINGS.items()))


def _held(file, variant, key, fmt="{:.2f} GB"):
    return V(file, ("variants", variant, "train", "between_calls") + tuple(key.split("/")), fmt)


_AMX_MEMORY = (("memory_cpu_amx.json", "tf_bfc_pool", "float32, oneDNN's BFC pool (the default)"),
               ("memory_cpu_amx.json", "system_allocator", "float32, every tensor from malloc"),
               ("memory_cpu_amx.json", "xla_bfc_pool", "float32, compile mode xla, BFC pool"),
               ("memory_cpu_amx_bf16.json", "tf_bfc_pool", "bfloat16, oneDNN's BFC pool"),
               ("memory_cpu_amx_bf16.json", "system_allocator", "bfloat16, every tensor from malloc"))
AMX_MEMORY_TABLE = Table(
    B, Quote(B, "`lab/tools/profile_memory.py --kinds train --steps 3` (`benchmarks/memory_cpu_amx.json`, and with "
                "`--set model.mixed_precision=true` `benchmarks/memory_cpu_amx_bf16.json`), paper config, {} points, "
                "batch 1, {}, family/model {} ({} cores; the runs shared the machine, so their times are not "
                "quoted):",
             (V("memory_cpu_amx.json", "points", "{:,}"), V("memory_cpu_amx.json", "cpu/model_name"),
              V("memory_cpu_amx.json", "cpu/family_model"), V("memory_cpu_amx.json", "cpu_count"))),
    ("setting", "peak in a step", "held between steps", "glibc: mapped blocks", "glibc: arenas",
     "TensorFlow's allocator: peak in use", "libraries (files)"), "lrrrrrr",
    tuple((what, V(file, ("variants", variant, "train", "timed", "peak_rss_gb"), "{:.2f} GB"),
           _held(file, variant, "rss_gb"), _held(file, variant, "mallinfo2/hblkhd"),
           _held(file, variant, "mallinfo2/arena"),
           Calc("{}", lambda gb: "none (malloc)" if not gb else f"{gb:.2f} GB",
                (_held(file, variant, "tf_allocator/peak_gb"),)),
           Calc("{:.2f} GB", lambda a, b: a + b, (_held(file, variant, "smaps_gb/file_tensorflow"),
                                                  _held(file, variant, "smaps_gb/file_other"))))
          for file, variant, what in _AMX_MEMORY))
TABLES += (AMX_STEP_TABLE, AMX_MEMORY_TABLE)
_AL, _AL1M = "latency_cpu_amx.json", "latency_cpu_amx_1m.json"
AMX_FORWARD = Quote(
    B, "The forward there, float32 (`lab/tools/benchmark_latency.py --modes auto,xla --points 32000 --train_points 0`, "
       "`benchmarks/" + _AL + "`, {}; and `--modes auto --points 1000000 --skip_conv_floor` in a process of its own, "
       "`benchmarks/" + _AL1M + "`): at 32,000 points `auto` ({}) takes {} the fastest convolution floor "
       "(XLA's, {} ms; that of the graph kernels hybrid's convolutions are, {} ms) and `xla` {}; at 1,000,000 "
       "points `auto` peaks at {}.",
    (V(_AL, "cpu/model_name"), V(_AL, "modes/auto/resolved"),
     V(_AL, "ratios/auto/min_points_over_fastest_conv_floor", "{:.2f}x"), V(_AL, "conv_floor/xla/median_ms", "{:,.0f}"),
     V(_AL, "conv_floor/graph/median_ms", "{:,.0f}"), V(_AL, "ratios/xla/min_points_over_fastest_conv_floor", "{:.2f}x"),
     V(_AL1M, "latency/1000000/auto/peak_rss_gb", "{:.2f} GB")))
QUOTES += (AMX_FORWARD,)

# -- the GRU head's cost beside the paper head (lab/tools/benchmark_head_cost.py); the note comes from the figures
_HC = "head_cost_cpu.json"
QUOTES += (
    Quote("docs/training.md", "On {} ({} cores, family/model {}; paper config, `model.compile=auto` -> {}, batch 1, "
                              "`benchmarks/head_cost_cpu.json`), in the tool's own words: {}",
          (V(_HC, "cpu/model_name"), V(_HC, "cpu/cpu_count"), V(_HC, "cpu/family_model"), V(_HC, "modes/inference"),
           V(_HC, "note"))),
)

# -- `make demo` on an AVX2-only CPU (tools/demo.py's demo_summary.json, issue 27's coffee-length first run)
_DEMO = "demo_zen3.json"
QUOTES += (
    Quote(B, "{}", (on_cpu(_DEMO, "demo/cpu"),)),
    Quote(B, "took {} s: {} s to install what the demo needs (`make install-core`, every package downloaded) and {} s "
             "for the demo, {} s of it training; the model's error on moving points is {} of zero flow's ({} vs {} "
             "m/s).",
          (V(_DEMO, "install_and_demo_seconds", "{:,.0f}"), V(_DEMO, "install_core_seconds", "{:,.0f}"),
           V(_DEMO, "demo/seconds", "{:,.0f}"), V(_DEMO, "demo/stage_seconds/train", "{:,.0f}"),
           V(_DEMO, "demo/moving_over_zero_flow", "{:.2f}"), V(_DEMO, "demo/moving_mean_l2_mps", "{:.2f}"),
           V(_DEMO, "demo/zero_flow_moving_mean_l2_mps", "{:.2f}"))),
)


def test_lookup_render_and_the_figure_pattern():
    data = {"latency": {"32000": {"auto/float32": {"ms": 1400.07}}}, "runs": [{"p": 1, "v": 2}, {"p": 2, "v": 3}],
            "by_int": {5: "five"}}
    assert lookup(data, "latency/32000/auto/float32/ms") == 1400.07  # a key holding "/"
    assert lookup(data, ("latency", "32000", "auto/float32", "ms")) == 1400.07
    assert lookup(data, "runs[p=2]/v") == 3 and lookup(data, "by_int/5") == "five"
    table = Table("d.md", Quote("d.md", "caption on a {}-core VM:", ("2",)), ("a", "b"), "lr", (("x", "1.5 s"),))
    assert table.text() == "caption on a 2-core VM:\n\n| a | b |\n|---|---:|\n| x | 1.5 s |"
    assert FIGURE_WITH_UNIT.findall("3.5 s, 1,234 ms, 4.1x, 12%, 0.5 m/s, 2.80 GB, 7.3 pairs/s; v2, 2-core") == \
        ["3.5 s", "1,234 ms", "4.1x", "12%", "0.5 m/s", "2.80 GB", "7.3 pairs/s"]


def _tables_of(text: str) -> list[str]:
    """Each Markdown table of a text (its consecutive lines starting with "|")."""
    return [m.group(0) for m in re.finditer(r"(?:^\|.*\n?)+", FENCE.sub("", text), re.M)]


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.header[0] + " / " + t.header[1])
def test_tables_are_rendered_from_their_json(table):
    # The rows exactly; the caption (wrapped as you like) right above them.
    text = read(table.doc)
    assert table.rows_text() in text and _flat(table.text()) in _flat(text), \
        f"{table.doc} must hold (the caption wrapped as you like):\n\n{table.text()}"


def _flat(text: str) -> str:
    """Whitespace runs as one space: a quoted sentence may be wrapped anywhere."""
    return " ".join(text.split())


@pytest.mark.parametrize("quote", QUOTES, ids=lambda q: q.template[:40])
def test_quoted_figures_are_their_json(quote):
    assert _flat(quote.text()) in _flat(read(quote.doc)), f"{quote.doc} must say (wrapped as you like): {quote.text()}"


def test_benchmarks_doc_has_no_other_table():
    rendered = [t.rows_text() for t in TABLES if t.doc == BENCHMARKS_DOC]
    extra = [t for t in _tables_of(read(BENCHMARKS_DOC)) if t.rstrip("\n") not in rendered]
    assert not extra, f"tables in {BENCHMARKS_DOC} not rendered by this test: {extra}"


FIGURE_WITH_UNIT = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?(?:e-?\d+)? ?(?:ms|s|GB|MB|TB|m/s|m|x|%|pairs/s)(?!\w)")


def test_benchmarks_doc_has_no_other_figure():
    text = FENCE.sub("", read(BENCHMARKS_DOC))
    for table in TABLES:
        text = text.replace(table.rows_text(), "")
    text = _flat(text)
    for quote in QUOTES + tuple(t.caption for t in TABLES):
        text = text.replace(_flat(quote.text()), "")
    text = CODE_SPAN.sub("", text)
    assert FIGURE_WITH_UNIT.findall(text) == [], "figures in docs/benchmarks.md that no JSON backs"


# --- The walk through one training step (docs/architecture.md) -----------------------------------------------------

STEP_FUNCTIONS = (  # (file, function or Class.method): from the command line to the optimizer's update
    ("tools/train.py", "main"),
    ("tools/_common.py", "start"),
    ("ff3d_tf/training/trainer.py", "Trainer.__init__"),
    ("ff3d_tf/model/fastflow3d.py", "build_model"),
    ("ff3d_tf/model/plan.py", "resolve"),
    ("ff3d_tf/training/trainer.py", "Trainer.train"),
    ("ff3d_tf/training/trainer.py", "Trainer._input_iterator"),
    ("ff3d_tf/training/input.py", "training_dataset"),
    ("ff3d_tf/training/trainer.py", "Trainer._run_step"),
    ("ff3d_tf/training/trainer.py", "Trainer.step"),
    ("ff3d_tf/training/trainer.py", "Trainer._step"),
    ("ff3d_tf/training/trainer.py", "Trainer._after_step"),
    ("ff3d_tf/training/trainer.py", "Trainer._replica_step"),
    ("ff3d_tf/training/trainer.py", "Trainer._state_variables"),
    ("ff3d_tf/model/step.py", "train_step_fn"),
    ("ff3d_tf/model/step.py", "loss_and_grads_fn"),
    ("ff3d_tf/model/forward.py", "model_inputs"),
    # the forward: the fused forward of the plan, stage by stage, and the layers that shape it
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.call"),
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.fused_forward"),
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.encode_points"),
    ("ff3d_tf/model/layers.py", "PointEncoder.call"),
    ("ff3d_tf/model/layers.py", "PointEncoder._encode_and_scatter"),
    ("ff3d_tf/model/ops.py", "chunked_segment_sum"),
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.grid_stages"),
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.unet"),
    ("ff3d_tf/model/layers.py", "ConvBlock.forward"),
    ("ff3d_tf/model/layers.py", "UpsampleSkip.into_next"),
    ("ff3d_tf/model/ops.py", "conv_chain_same"),
    ("ff3d_tf/model/fastflow3d.py", "FastFlow3D.decode_points"),
    ("ff3d_tf/model/losses.py", "batch_flow_loss"),
    ("ff3d_tf/model/losses.py", "per_sample_training_loss"),
    ("ff3d_tf/model/losses.py", "per_sample_flow_loss"),
    ("ff3d_tf/model/losses.py", "point_weights"),
    ("ff3d_tf/training/trainer.py", "_over_replicas"),
    ("ff3d_tf/model/step.py", "adam_update"),
    ("ff3d_tf/model/step.py", "learning_rate_schedule"),
    ("ff3d_tf/model/step.py", "adam_apply"),
    ("ff3d_tf/training/trainer.py", "Trainer._assign_step_result"),
)


def function_lines(rel: str, qualname: str) -> int:
    """Lines of the definition of `qualname` in `rel`: a function or a class's method defined there (a name the
    module imports or assigns is not counted as its function)."""
    scope, node = _top_level_names(module_tree(rel).body), None
    for name in qualname.split("."):
        node = scope[name]
        scope = _top_level_names(node.body) if isinstance(node, ast.ClassDef) else {}
    assert isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)), f"{rel}: {qualname} is not defined there"
    return node.end_lineno - node.lineno + 1


def step_walk_sentence() -> str:
    files = {f for f, _ in STEP_FUNCTIONS}
    lines = sum(function_lines(f, q) for f, q in STEP_FUNCTIONS)
    return f"{len(STEP_FUNCTIONS)} functions in {len(files)} files, {lines} lines"


def test_the_step_walk_names_its_functions_and_counts_them():
    text = read("docs/architecture.md")
    missing = [f"{f}: {q}" for f, q in STEP_FUNCTIONS
               if not re.search(r"`(%s|%s)[`(]" % (re.escape(q), re.escape(q.split(".")[-1])), text)]
    assert not missing, f"docs/architecture.md does not name {missing}"
    assert _flat(step_walk_sentence()) in _flat(text), f"docs/architecture.md must say: {step_walk_sentence()}"


if __name__ == "__main__":
    for item in TABLES + QUOTES:
        print(f"--- {item.doc}\n{item.text()}\n")
    print(f"--- docs/architecture.md\n{step_walk_sentence()}")
