.PHONY: setup test test-slow lint format demo

setup:
	bash scripts/setup.sh

test:
	bash scripts/test.sh

test-slow:
	bash scripts/setup.sh && HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 .venv/bin/python -m pytest -q -m slow

lint:
	.venv/bin/ruff check openfly_agent tests bench train.py eval.py && .venv/bin/ruff format --check openfly_agent tests bench train.py eval.py

format:
	.venv/bin/ruff check --fix openfly_agent tests bench train.py eval.py && .venv/bin/ruff format openfly_agent tests bench train.py eval.py

demo:
	bash scripts/main_job.sh
