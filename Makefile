# The course's commands. The two a newcomer needs:
#   make lab    set up .venv (first time only) and open JupyterLab on notebooks/
#   make test   set up .venv (first time only) and run every test
# A learner starts with `make lab-student` (the exercises unsolved, in student/).
#
# torch and torchvision are installed first, on their own, so you choose the build
# that fits your machine (README.md, "Two commands"): the default takes them
# from PyPI; on Linux a CPU-only build comes from PyTorch's CPU index,
#   make lab TORCH="torch==2.14.1 torchvision==0.29.1 --index-url https://download.pytorch.org/whl/cpu"
# Their versions are then written to .venv/constraints.txt and every later
# install is constrained by them, so no dependency can swap them for another build.
# (The course's development machines hold this default pair on their own disk.)

PYTHON ?= python3
TORCH ?= torch==2.14.1 torchvision==0.29.1
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup lab lab-student fetch-data test test-fast book student bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet $(TORCH)
	$(BIN)/python -c "import importlib.metadata as m; [print(p + '==' + m.version(p)) for p in ('torch', 'torchvision')]" > $(VENV)/constraints.txt
	$(BIN)/python -m pip install --quiet --constraint $(VENV)/constraints.txt --editable ".[test,book]"
	touch $@

# Jupyter refuses to run as root unless told; containers and CI machines often are root.
ROOT_FLAG := $(if $(filter 0,$(shell id -u)),--allow-root,)

lab: setup
	$(BIN)/jupyter lab $(ROOT_FLAG) $(LAB_ARGS) notebooks/

# The learner's path: the student versions (exercises left as stubs; your edits are kept).
lab-student: student
	$(BIN)/jupyter lab $(ROOT_FLAG) $(LAB_ARGS) student/

# Unit tests; every notebook run by nbval at ci scale (each executed once: the book's test
# renders them without running them again); the student versions run to the end; the book
# read in a browser. pytest-xdist spreads the files over one single-threaded worker per core
# (at most 4): at ci scale a test waits on Python and kernels far more than on arithmetic.
# conftest.py keeps files whole but makes each notebook's student rerun a unit of its own,
# and hands the longest units out first.
# -v names every item, so the log shows each notebook cell that nbval ran.
NBVAL := --nbval-lax --nbval-current-env --nbval-cell-timeout=900
test: setup fetch-data
	EBJEPA_SCALE=ci MPLBACKEND=agg OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=1 $(BIN)/python -m pytest \
		-p no:cacheprovider -v -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder \
		--durations=15 \
		tests notebooks $(NBVAL)

# The datasets, downloaded (or decoded from EBJEPA_DATA's copy) once, before the tests'
# parallel workers read them: two workers downloading one archive at once would corrupt it.
fetch-data: setup
	$(BIN)/python -c "from ebjepa_tutorial.data import load_cifar10, load_mnist; \
		[load_cifar10(split) for split in ('train', 'test')]; load_mnist('test')"

# The fast unit tests (under 30 s on 2 idle cores), for quick edit-test loops; `slow` marks the rest.
# Spread like `test` (--dist load: the fast tests are many and short, so per test, not per file).
# No nbval: it runs no notebook here, and loading it (nbformat, jsonschema) costs each process
# one to several seconds before the first test (research/notes/2026-12-07-thin-package-10.md).
test-fast: setup
	MPLBACKEND=agg OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=1 $(BIN)/python -m pytest tests \
		-q -n auto --maxprocesses 4 -m "not slow and not browser" -p no:nbval

book: setup
	$(BIN)/python -m tools.book build

# Writes student/NN_*.ipynb for every chapter; one that exists (your work) is kept.
student: setup
	$(BIN)/python -m tools.student notebooks student

bench: setup
	for script in research/benchmarks/[a-z]*.py; do \
		name=$$(basename $$script .py); \
		case $$name in video_full|timing) continue;; esac; \
		$(BIN)/python -m research.benchmarks.$$name || exit 1; done  # video_full: for a GPU; timing: a helper

lint: setup
	$(BIN)/ruff check ebjepa_tutorial research tools tests notebooks

clean:
	rm -rf build student .jupyter_cache
