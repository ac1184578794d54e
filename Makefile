# Two entry points: `make demo` (main job on the embedded synthetic default) and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CORE_STAMP := $(VENV)/.installed-core-v1
STAMP := $(VENV)/.installed-v1

.PHONY: install install-core test test-slow demo clean

# install-core: TensorFlow, the Waymo protos (the synthetic segments are WOD Frames) and what the main job needs
# (`make demo`); install: also the tests' and every tool's extras (Beam, JAX, ONNX, Rerun).
install-core: $(CORE_STAMP)
install: $(STAMP)

$(CORE_STAMP): setup.py constraints.txt Makefile
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e .
	$(PY) -m pip install -q --no-deps waymo-open-dataset-tf-2-12-0==1.6.7
	touch $(CORE_STAMP)

$(STAMP): $(CORE_STAMP)
	$(PY) -m pip install -q -c constraints.txt -e ".[dev,beam,xla,onnx,viz3d,selfsup]"
	touch $(STAMP)

# Test files run on TEST_WORKERS processes (pytest-xdist, whole files per process, as Bazel runs its targets side by
# side): 1.75x faster than one process on this project's 2-core machines.
TEST_WORKERS ?= 2
# EMULATE_CPU=zen3 caps oneDNN and XLA to AVX2 and turns TensorFlow's oneDNN operations off, as they are on an AMD
# Zen 3 (ff3d_tf/cpu.py, EMULATIONS), for `make test` and `make demo`; the suite prints the CPU and the caps it ran
# under, the demo writes them into demo_out/demo_summary.json.
EMULATE_CPU ?=
EMULATION = $(PY) -c "from ff3d_tf import cpu; print(cpu.emulation_env('$(EMULATE_CPU)'))"
CPU_ENV = $(if $(EMULATE_CPU),env $$($(EMULATION)),)

test: install
	@$(if $(EMULATE_CPU),$(EMULATION) >/dev/null,true)
	$(CPU_ENV) $(PY) -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile --durations=15 tests

test-slow: install
	$(PY) -m pytest -q -m slow tests

# CI's further legs (.ci/run). test-zen3: the numerically sensitive test files (optimiser and training steps, the
# trainer, replicas and workers, XLA against TensorFlow, the plan against the table, NSFP) again under the zen3 caps,
# so a failure that only an AVX2 CPU shows is seen on any machine. test-distributed: the tests marked slow that guard
# distributed training's equivalence to one model (replicas, workers, resumes).
SENSITIVE_TESTS = tests/model/test_step.py tests/model/test_plan.py tests/model/test_compile.py \
	tests/model/test_conv_forms.py tests/model/test_precision.py tests/model/test_remat.py \
	tests/training/test_trainer.py tests/training/test_distributed.py tests/training/test_multiworker.py \
	tests/training/test_gru_head_training.py tests/training/test_xla_step.py tests/inference/test_xla_export.py \
	tests/labels/test_nsfp.py
DISTRIBUTED_TESTS = tests/training/test_distributed.py tests/training/test_multiworker.py \
	tests/training/test_gru_head_training.py
ZEN3_ENV = env $$($(PY) -c "from ff3d_tf import cpu; print(cpu.emulation_env('zen3'))")

.PHONY: test-zen3 test-distributed
test-zen3: install
	$(ZEN3_ENV) $(PY) -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile $(SENSITIVE_TESTS)

test-distributed: install
	$(PY) -m pytest -q -m slow -n $(TEST_WORKERS) --dist loadfile $(DISTRIBUTED_TESTS)

# test-docs-commands: every command of docs/datasets.md, docs/training.md and docs/deployment.md run as written on small
# synthetic data
# (tests/tools/test_docs_commands.py), and the slow tests of the tools users run with several sweeps and Argoverse 2
# records (predict, eval, the submission, the record jobs, the exports' sweep order, every export of the recipes' model).
COMMANDS_TESTS = tests/tools/test_docs_commands.py tests/tools/test_several_sweeps_tools.py \
	tests/tools/test_predict_sequences.py tests/tools/test_record_jobs.py tests/inference/test_sequence_serving.py
# COMMANDS_SELECT: a pytest -k expression (CI leaves out the longest: .ci/run says which).
COMMANDS_SELECT ?=
.PHONY: test-docs-commands
test-docs-commands: install
	$(PY) -m pytest -q -m slow -n $(TEST_WORKERS) --dist loadfile $(if $(COMMANDS_SELECT),-k "$(COMMANDS_SELECT)",) \
		$(COMMANDS_TESTS)

# MODEL=gru: the demo with DeFlow's GRU head (tools/demo.py --model gru) instead of the paper's.
MODEL ?= paper
DEMO_OUT ?= demo_out

demo: install-core
	@$(if $(EMULATE_CPU),$(EMULATION) >/dev/null,true)
	$(CPU_ENV) $(PY) tools/demo.py --out_dir $(DEMO_OUT) --model $(MODEL)

clean:
	rm -rf $(DEMO_OUT) .pytest_cache

# Bazel (docs/bazel.md): Debian's bazel-bootstrap (Bazel 4.2.3) runs the tests offline on the same .venv, one target
# per test file; tests marked slow stay out (--test_tag_filters in .bazelrc). BAZEL_STARTUP takes startup options
# (e.g. --output_base=DIR), BAZEL_FLAGS test options, BAZEL_TARGETS the target patterns.
BAZEL ?= bazel
BAZEL_STARTUP ?=
BAZEL_FLAGS ?=
BAZEL_TARGETS ?= //...
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: bazel-test
bazel-test: install
	@command -v $(BAZEL) >/dev/null 2>&1 || $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -q bazel-bootstrap \
		|| { $(SUDO) apt-get update -q && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -q bazel-bootstrap; }
	$(PY) tools/check_bazel_targets.py
	$(BAZEL) $(BAZEL_STARTUP) test --nocache_test_results $(BAZEL_FLAGS) $(BAZEL_TARGETS)
