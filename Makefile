# Front door. `make demo` runs the main job, `make test` runs the tests (`make acceptance`: the issues' gates).
# Both build their own environment (.venv) from the pinned requirements.lock.
PYTHON ?= python3
VENV   ?= .venv
STAMP  := $(VENV)/.installed
OUT    ?= results

.PHONY: demo test acceptance bench env clean

$(STAMP): requirements.lock setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet --require-virtualenv -r requirements.lock
	$(VENV)/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

env: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/touchdown demo --out $(OUT)

test: $(STAMP)
	$(VENV)/bin/python scripts/run_tests.py

acceptance: $(STAMP)
	$(VENV)/bin/python scripts/run_tests.py --acceptance

bench: $(STAMP)
	$(VENV)/bin/python bench/ekf_cost.py

clean:
	rm -rf $(VENV) $(OUT)
