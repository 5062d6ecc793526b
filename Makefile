# recon — the README's commands. Everything runs inside .venv, created by `make install`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
export OMP_NUM_THREADS ?= 2

.PHONY: install test test-all lint docs demo bench sweep browser clean gpu-wheels gpu-check

install: $(BIN)/recon

$(BIN)/recon: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch pinned in the SAME pip call as every other dependency, so nothing pulls a CUDA build.
	$(BIN)/pip install -q torch==2.13.0 -e '.[test]'
	@touch $@

# two xdist workers on two cores: one thread each, or OpenMP oversubscription costs 10-40x.
# `make test`: the fast tier (every unit test; not the tests marked slow: end to end on real
# data, whole training runs); `make test-all`: everything, what CI runs.
PYTEST := OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile
test: lint docs
	$(PYTEST) -m "not slow" tests

test-all: lint docs
	$(PYTEST) tests

# the docs site (mkdocs.yml) into site/; --strict: a broken link or a missing page fails. The
# reference pages are made from the code at build time (docs/hooks/reference.py). The variable
# silences Material's banner about MkDocs 2.0, printed on every build. Not --quiet: it hides the
# warnings that --strict counts, and the build passes whatever they say.
docs: install
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -d site

# Debian's chromium + chromedriver for the report.html browser test (skipped, with the reason,
# where they are missing); needs root or sudo, as CI has
browser:
	@if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then \
		echo "chromium and chromedriver present"; \
	else \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium chromium-driver >/dev/null; \
	fi

# ruff (lint and format), and the layer order of pyproject.toml's import-linter contract
lint: install
	$(BIN)/ruff check recon tests pipelines docs
	$(BIN)/ruff format --check recon tests pipelines docs
	$(BIN)/lint-imports

# the product at its best on the project's own scene, as a user runs it on theirs (`recon run`):
# sfm from its photos, 3dgs, an orbit video, a mesh, eval against the known poses and mesh ->
# workspaces/sample-photos/report.html; a second `make demo` skips what is done and fresh
demo: install
	$(BIN)/recon run sample_data/images -w workspaces/sample-photos --method $(or $(METHOD),3dgs) \
	    --time-budget $(or $(BUDGET),120) --orbit-frames 60 \
	    --gt-poses sample_data/transforms.json --gt-mesh sample_data/mesh.ply

# Snakemake over sample_data/ x every method with short budgets (pipelines/config.yaml):
# results/sweep/table.md and one speed-vs-error plot per scene
sweep: install
	$(BIN)/snakemake -s pipelines/Snakefile --configfile pipelines/config.yaml --cores 2

# lego-200 (every method) + sfm on sample/fox, render throughput of those lego-200 runs (200 and
# 800 px), the real captures (3dgs and ngp), the fox-real 30-minute model in the report's 3D
# viewer (headless chromium), then meshes against ground truth (sample_data and the walnut
# ring) and sample_data's mesh F-score against training time
bench: install browser
	$(BIN)/python pipelines/bench.py
	$(BIN)/python pipelines/bench_render.py
	$(BIN)/python pipelines/bench_real.py
	$(BIN)/python pipelines/bench_viewer.py -w bench/work/fox-real --run 3dgs-1800
	$(BIN)/python pipelines/bench_mesh.py --methods ngp,plenoxel,3dgs,sdf,mvs
	$(BIN)/python pipelines/bench_mesh.py --scenes sample --methods sdf,3dgs --curve 60,120,300,600

# Wheels for a GPU machine without network (`make gpu-check` installs from them only what that
# machine lacks, never its torch): recon's dependencies with theirs, for GPU_PY on x86-64 Linux,
# and gsplat and pytorch-msssim without theirs (torch), into .gpu-wheels/
GPU_PY ?= 3.12
GPU_WHEELS ?= .gpu-wheels
GPU_PLATFORMS := $(foreach p,manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64,--platform $(p))
GPU_DOWNLOAD = $(PY) -m pip download -q --only-binary=:all: --python-version $(GPU_PY) \
	--implementation cp $(GPU_PLATFORMS) -d $(GPU_WHEELS)
gpu-wheels: install
	mkdir -p $(GPU_WHEELS)
	$(GPU_DOWNLOAD) numpy click rich 'pycolmap>=3.12,<5' 'opencv-contrib-python-headless>=4.8,<5' \
		OpenEXR trimesh scipy scikit-image matplotlib numba imageio imageio-ffmpeg pillow jaxtyping
	$(GPU_DOWNLOAD) --no-deps gsplat==1.5.3 pytorch-msssim
	# LPIPS's weights, converted here (recon fetches them with pip, which needs a network)
	$(BIN)/python -c "from recon.metrics.lpips import ensure_lpips_weights as w; import shutil; shutil.copy(w(), '$(GPU_WHEELS)')"
	@ls $(GPU_WHEELS) | wc -l | xargs echo "wheels in $(GPU_WHEELS):"

# On a machine with an NVIDIA GPU, nvcc and a CUDA build of torch (python3 there): installs what
# is missing from .gpu-wheels/, compiles gsplat, trains every method on lego-400 and 3dgs on fox,
# writes bench/results/<date>-gpu-check-<gpu>.json (pipelines/gpu_check.py)
gpu-check:
	python3 pipelines/gpu_check.py --wheels $(GPU_WHEELS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .gpu-site site
