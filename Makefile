# The two commands of the README. ARGS passes options to plvo-viz, e.g. make run ARGS="--seq 04 --root ../shared/data/kitti".
.PHONY: run test test-busy test-bits bench lint
run:
	bash scripts/setup.sh && .venv/bin/plvo-viz $(ARGS)
# The lint and type checks first (seconds), then the suite
test:
	bash scripts/setup.sh --test && .venv/bin/ruff check plvo plvo_app plvo_eval plvo_synth tests scripts && .venv/bin/mypy && \
	.venv/bin/python -m pytest -q -p no:cacheprovider $(ARGS)
# The suite with a busy loop on one core throughout (the bounds hold on a loaded machine too)
test-busy:
	bash scripts/setup.sh --test && bash scripts/test_busy.sh $(ARGS)
# The suite on AVX2 kernels (other last bits than this machine's, as another machine kind gives)
test-bits:
	bash scripts/setup.sh --test && bash scripts/test_other_bits.sh $(ARGS)
bench:
	bash scripts/setup.sh && .venv/bin/plvo bench $(ARGS)
# Style (ruff, the rules in pyproject.toml) and types (mypy on plvo/, plvo_eval/ and plvo_synth/: pyproject.toml)
lint:
	bash scripts/setup.sh --test && .venv/bin/ruff check plvo plvo_app plvo_eval plvo_synth tests scripts && .venv/bin/mypy
