# Every target creates or reuses .venv and installs what it needs; nothing relies
# on what happens to be installed on the machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench paper samples clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

SAMPLE := sample_sequences/occlusion

demo: $(STAMP)
	rm -rf demo-out && mkdir -p demo-out
	$(BIN)/condtrack track $(SAMPLE) -p $(SAMPLE)/queries.csv -o demo-out/occlusion.h5 --overlay demo-out/occlusion.mp4
	$(BIN)/condtrack track $(SAMPLE) -p $(SAMPLE)/queries.csv -o demo-out/occlusion.csv -q
	$(BIN)/condtrack eval demo-out/occlusion.h5 $(SAMPLE)/tracks.csv
	@echo "demo outputs: $(CURDIR)/demo-out/occlusion.h5 $(CURDIR)/demo-out/occlusion.csv $(CURDIR)/demo-out/occlusion.mp4"

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python -m condtrack_cli.evaluate.bench --out bench/results.md

# The paper's own scenes (Oxford corridor, flower garden; ../shared/data, no ground truth): STK, CLF and CNLF
# from Shi-Tomasi points of frame 0, contact sheets, overlays and the forward-backward round trip (docs/paper.md).
paper: $(STAMP)
	$(BIN)/python -m condtrack_cli.evaluate.paper_figures --out paper_figures

samples: $(STAMP)
	$(BIN)/condtrack synth sample_sequences --samples --force

clean:
	rm -rf $(VENV) demo-out paper_figures .pytest_cache
