# Everything bootstraps itself: uv is installed with pip when missing, then `uv sync` builds the venv.
UV = $(shell command -v uv 2>/dev/null || echo python3 -m uv)
PYTEST_WORKERS ?= 2

.PHONY: setup demo test lint format bench regression

setup:
	@command -v uv >/dev/null 2>&1 || python3 -m uv --version >/dev/null 2>&1 || python3 -m pip install -q uv
	@$(UV) sync --frozen --compile-bytecode -q

demo: setup
	$(UV) run uwbcal demo

lint: setup
	$(UV) run ruff check .
	$(UV) run ruff format --check .

test: lint
	$(UV) run pytest -n $(PYTEST_WORKERS) --dist loadgroup

format: setup
	$(UV) run ruff check --fix .
	$(UV) run ruff format .

bench: setup
	$(UV) run uwbcal bench -o recordings/bench.json

# Re-run the small seeded experiment and compare it with the committed reference (exit 1 on a regression).
regression: setup
	$(UV) run uwbcal experiment ri-vs-lsi --runs 8 --seed 0 -o recordings/ci/ri-vs-lsi
	$(UV) run uwbcal diff recordings/reference/ri-vs-lsi/summary.json recordings/ci/ri-vs-lsi/summary.json --rtol 0.05
	$(UV) run uwbcal experiment anchor-nees --runs 8 --seed 0 --param pose_sources=groundtruth,odometry,msckf --jobs 2 -o recordings/ci/anchor-nees
	$(UV) run uwbcal diff recordings/reference/anchor-nees/summary.json recordings/ci/anchor-nees/summary.json --rtol 0.05
