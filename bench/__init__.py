"""The project's benchmarks: speed, accuracy and quality, each written to ``bench/results/``
with one header (``bench.machine``). Run from the repository as ``python -m bench <name> ...``
(``python -m bench --help`` lists them); ``python -m bench report`` rewrites the tables the docs
include from the result files."""
