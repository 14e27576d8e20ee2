# The course's commands. The two a newcomer needs:
#   make lab    set up .venv (first time only) and open JupyterLab on notebooks/
#   make test   set up .venv (first time only) and run every test
# A learner starts with `make lab-student` (the exercises unsolved, in student/).
#
# torch is installed first, on its own, so you choose the build that fits your
# machine, e.g. `make lab TORCH="torch==2.13.0"` (the default, a CPU build) or
# `make lab TORCH="torch --index-url https://download.pytorch.org/whl/cu124"`.
# Its version is then written to .venv/constraints.txt and every later install
# is constrained by it, so no dependency can swap torch for another build.

PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup lab lab-student test test-fast book student bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet $(TORCH)
	$(BIN)/python -c "import importlib.metadata as m; print('torch==' + m.version('torch'))" > $(VENV)/constraints.txt
	$(BIN)/python -m pip install --quiet --constraint $(VENV)/constraints.txt --editable ".[test,book]"
	touch $@

# Jupyter refuses to run as root unless told; containers and CI machines often are root.
ROOT_FLAG := $(if $(filter 0,$(shell id -u)),--allow-root,)

lab: setup
	$(BIN)/jupyter lab $(ROOT_FLAG) $(LAB_ARGS) notebooks/

# The learner's path: the student versions (exercises left as stubs; your edits are kept).
lab-student: student
	$(BIN)/jupyter lab $(ROOT_FLAG) $(LAB_ARGS) student/

# Unit tests, every notebook (teacher's and student's) at ci scale, and the book in a browser.
# The book's build executes each notebook top to bottom, so nbval would only run them again.
test: setup
	EBJEPA_SCALE=ci $(BIN)/python -m pytest -p no:cacheprovider --durations=15

# The fast unit tests (under 30 s on 2 idle cores), for quick edit-test loops; `slow` marks the rest.
test-fast: setup
	$(BIN)/python -m pytest tests -m "not slow and not browser"

book: setup
	$(BIN)/python -m ebjepa_tutorial.course.book build

# Writes student/NN_*.ipynb for every chapter; one that exists (your work) is kept.
student: setup
	$(BIN)/python -m ebjepa_tutorial.course.student notebooks student

bench: setup
	for script in benchmarks/*.py; do $(BIN)/python $$script || exit 1; done

lint: setup
	$(BIN)/ruff check ebjepa_tutorial tests benchmarks notebooks

clean:
	rm -rf build student .jupyter_cache
