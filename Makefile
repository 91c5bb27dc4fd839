# rebar-servo: two commands on a fresh machine, `make dataset` and `make test`, do the whole set-up.
SHELL := /bin/bash
# a pipe fails when any part of it fails (a build piped into tee fails as the build does)
.SHELLFLAGS := -o pipefail -c
PY := .venv/bin/python
REBAR := .venv/bin/rebar
STAMP := .venv/.installed
# Open3D's EGL renderer, then the X11 client libraries Blender's bpy (the Cycles renderer) loads
DEB_PKGS := libegl1 libgl1 libgl1-mesa-dri libegl-mesa0 libgomp1 libx11-6 libxext6 libxrender1 libxxf86vm1 libxfixes3 libxi6 libxkbcommon0 libsm6
export EGL_PLATFORM ?= surfaceless
DATA ?= data
WORKERS ?= $(shell nproc)

.PHONY: map setup system-deps dataset smoke mesh train built eval tour element test check format bench clean

setup: system-deps $(STAMP)

# Debian packages the renderers need; installed only when missing (needs root or sudo).
system-deps:
	@missing=$$(for p in $(DEB_PKGS); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages: $$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	# torch first: the CPU wheel, so that the package's torch requirement never pulls a CUDA build
	$(PY) -m pip install -q torch==2.13.0
	# the ray extra too: the tests prove the Ray backend builds what the local one does; cycles
	# (Blender's bpy, a 519 MB wheel): the tests render with it and score the shipped detector on its frames;
	# and ifc (IfcOpenShell): the tests write and read IFC rebar models
	$(PY) -m pip install -q -e ".[dev,ray,cycles,ifc]"
	@touch $(STAMP)

$(DATA):
	@mkdir -p $@

mesh: setup
	$(REBAR) mesh pipelines/paper-tunnel.yaml --out $(DATA)/mesh/paper-tunnel

dataset: setup | $(DATA)
	$(REBAR) dataset build pipelines/paper-tunnel.yaml --out $(DATA) --workers $(WORKERS) --resume | tee $(DATA)/.last-build
	$(REBAR) dataset validate "$$(tail -1 $(DATA)/.last-build)"
	$(REBAR) dataset audit "$$(tail -1 $(DATA)/.last-build)"

smoke: setup | $(DATA)
	$(REBAR) dataset build pipelines/smoke.yaml --out $(DATA) --workers $(WORKERS) --force | tee $(DATA)/.last-smoke
	$(REBAR) dataset validate "$$(tail -1 $(DATA)/.last-smoke)"
	$(REBAR) dataset audit "$$(tail -1 $(DATA)/.last-smoke)"

# Train the detector on the default dataset (built first when missing) and its supplements (built when
# missing: the lower-mat one, 720 images, about 5 minutes; the four wide-randomization ones, 180 images each,
# about 3 minutes each) and, for the first stage (its epochs and adapt epochs) and the second stage, the Cycles-rendered
# supplements (REFINE_SUPPLEMENTS, built when missing with one worker, as Cycles takes both cores: 36 or 48
# images each, 7-11 minutes each), and
# ship it with its model card, scored also on the planar-slab set (another config, built when missing: 90
# images, a minute) and on the Cycles-rendered cross-renderer sets, from RGB alone, with depth and with what lies
# behind flattened (built when missing: about 20 minutes; 26 on a CPU without AVX-512). See the model card for
# the training time on 2 cores.
# Run again after a kill, it picks up where it stopped: an interrupted dataset build goes on (--resume), each
# stage's epochs from its checkpoint, each finishing and card step from runs/train/paper-tunnel/steps.json.
# `rebar train DATASET --init` starts from the shipped model instead (README, "Fine-tune on your own bars").
# the site-* sets: the bars sites use (8-40 mm at 100-400 mm, seen from 0.3-1.5 m), 240 images each
SUPPLEMENTS := paper-tunnel-lower-mat wide-tunnel-a wide-tunnel-b wide-planar-a wide-planar-b \
	site-planar-heavy site-tunnel-heavy site-planar-light
REFINE_SUPPLEMENTS := cycles-train-tunnel cycles-train-planar cycles-train-tunnel-b cycles-train-planar-b \
	cycles-train-tunnel-c cycles-train-planar-c cycles-train-tunnel-d cycles-train-planar-d \
	cycles-site-planar-heavy
# held out, never trained on, scored for the card: heavy bars (25-40 mm) and light bars seen from far
HELD_OUT := heavy-bars far-light-bars
# the line check (scores read along each detection's bars, without depth) is fitted on the val split and
# these: the Cycles sets with a lower mat in every scene, whose top-over-lower places it is for
LINE_SUPPLEMENTS := cycles-train-tunnel-d cycles-train-planar-d
train: setup
	@ver=$$(sed -n 's/^version: *//p' pipelines/paper-tunnel.yaml | head -1); ds=$(DATA)/paper-tunnel/v$$ver; \
	if [ ! -d "$$ds" ]; then $(MAKE) --no-print-directory dataset || exit 1; fi; \
	sup=""; for p in $(SUPPLEMENTS); do sup="$$sup --supplement $$($(MAKE) --no-print-directory -s built PIPELINE=$$p)" || exit 1; done; \
	for p in $(REFINE_SUPPLEMENTS); do sup="$$sup --refine-supplement $$($(MAKE) --no-print-directory -s built PIPELINE=$$p WORKERS=1)" || exit 1; done; \
	for p in $(LINE_SUPPLEMENTS); do sup="$$sup --line-supplement $$($(MAKE) --no-print-directory -s built PIPELINE=$$p WORKERS=1)" || exit 1; done; \
	gen=$$($(MAKE) --no-print-directory -s built PIPELINE=planar-slab) || exit 1; \
	for p in $(HELD_OUT); do gen="$$gen --eval $$($(MAKE) --no-print-directory -s built PIPELINE=$$p)" || exit 1; done; \
	cv=""; for p in $(CROSSVAL); do cv="$$cv --eval $$($(MAKE) --no-print-directory -s built PIPELINE=$$p WORKERS=1)" || exit 1; done; \
	$(REBAR) train "$$ds" $$sup --out runs/train/paper-tunnel --ship --eval $$gen $$cv

# Prints the folder of pipelines/$(PIPELINE).yaml's build, building it first when missing (an interrupted build
# goes on where it stopped; used by train).
built: setup
	@ver=$$(sed -n 's/^version: *//p' pipelines/$(PIPELINE).yaml | head -1); ds=$(DATA)/$(PIPELINE)/v$$ver; \
	if [ ! -d "$$ds" ]; then $(REBAR) dataset build pipelines/$(PIPELINE).yaml --out $(DATA) --workers $(WORKERS) --resume >&2 || exit 1; fi; \
	echo "$$ds"

# Servo evaluation: the paper's set-up (shipped detector), the same with a lower bar mat under the top one,
# and the randomized suite with detector faults, each checked against eval/thresholds.yaml. Outputs
# (tables, plots, .rrd recordings) go to $(EVAL_OUT).
EVAL_OUT ?= runs/eval
eval: setup
	$(REBAR) servo run eval/paper.yaml --out $(EVAL_OUT)/paper
	$(REBAR) servo check $(EVAL_OUT)/paper
	$(REBAR) servo run eval/paper-lower-mat.yaml --out $(EVAL_OUT)/paper-lower-mat
	$(REBAR) servo check $(EVAL_OUT)/paper-lower-mat
	$(REBAR) servo run eval/random.yaml --out $(EVAL_OUT)/random
	$(REBAR) servo check $(EVAL_OUT)/random

# Tours (docs/servo.md, "Tours"): every crossing in reach tied once, on the paper's segment (with and without its
# lower mat) and on two decks seen from above; each run then held to eval/thresholds.yaml.
TOURS := tour-paper tour-paper-lower-mat tour-deck tour-deck-16mm
tour: setup
	@for t in $(TOURS); do \
	  $(REBAR) servo run eval/$$t.yaml --out $(EVAL_OUT)/$$t && $(REBAR) servo check $(EVAL_OUT)/$$t || exit 1; \
	done

# The servo map of the paper's segment (eval/map-paper.yaml, docs/servo.md "Where servoing holds"): 200 episodes,
# IBVS and PBVS over the segment, two camera views and two turns of the segment, on $(MAP_WORKERS) local workers
# (about 20 minutes on 2 cores); run again after a stop, it resumes. `--backend ray` runs it on a Ray cluster.
MAP_WORKERS ?= 2
map: setup
	$(REBAR) servo map eval/map-paper.yaml --out $(EVAL_OUT)/map-paper --workers $(MAP_WORKERS)

# The whole paper segment tied from 20 base poses (eval/element-paper.yaml): the loop's reach and coverage, on the
# exact detector and ray-cast frames; about 25 minutes on 2 cores.
element: setup
	$(REBAR) servo run eval/element-paper.yaml --out $(EVAL_OUT)/element-paper
	$(REBAR) servo check $(EVAL_OUT)/element-paper

# pytest exits 5 when it collects no tests: a broken suite, reported as a failure.
test: setup
	@$(PY) -m pytest -q; rc=$$?; if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 1; fi; exit $$rc

check: setup
	.venv/bin/ruff format --check rebar_data tests
	.venv/bin/ruff check rebar_data tests

format: setup
	.venv/bin/ruff format rebar_data tests
	.venv/bin/ruff check --fix rebar_data tests

bench: setup
	$(REBAR) bench

clean:
	rm -rf .pytest_cache .ruff_cache

# Cross-renderer validation sets (pipelines/crossval-*.yaml): the same meshes, cameras and labels as a training
# set, the RGB images rendered by Blender Cycles (installed by setup), every image in the test split. Builds each
# set when missing (24 images, 5-15 minutes on 2 cores), validates and audits it, then scores the shipped
# detector on it from RGB alone: its sight points against the labels and against the projected 3D crossing
# points, and its crossing-point stage's points against the 3D points; and with each depth sensor model's image
# of the scene (`rebar score --depth-from`; predictions and metrics in $(CROSSVAL_OUT)).
CROSSVAL := crossval-planar crossval-tunnel
CROSSVAL_OUT ?= runs/crossval
.PHONY: crossval

crossval: setup | $(DATA)
	@mkdir -p $(CROSSVAL_OUT)
	@for p in $(CROSSVAL); do \
	  ver=$$(sed -n 's/^version: *//p' pipelines/$$p.yaml | head -1); ds=$(DATA)/$$p/v$$ver; \
	  if [ ! -d "$$ds" ]; then $(REBAR) dataset build pipelines/$$p.yaml --out $(DATA) --workers 1 || exit 1; fi; \
	  $(REBAR) dataset validate "$$ds" || exit 1; \
	  $(REBAR) dataset audit "$$ds" || exit 1; \
	  for tp in sight:sight crossing:sight crossing:crossing; do t=$${tp%:*}; pt=$${tp#*:}; \
	    $(REBAR) score "$$ds" --split test --no-depth --truth $$t --point $$pt --quiet \
	      --out $(CROSSVAL_OUT)/$$p.$$pt.parquet --metrics $(CROSSVAL_OUT)/$$p.$$t-truth.$$pt-points.json >/dev/null || exit 1; \
	  done; \
	  for src in structured_light active_stereo time_of_flight; do \
	    $(REBAR) score "$$ds" --split test --depth-from $$src --quiet --out $(CROSSVAL_OUT)/$$p.depth-$$src.parquet \
	      --metrics $(CROSSVAL_OUT)/$$p.depth-$$src.json >/dev/null || exit 1; \
	  done; \
	done
