"""The run lifecycle: a run's settings (``config``), its entry point (``train``), the checks and
resolution before a run (``prepare``) and the loop itself (``loop``), sweeps of runs
(``sweep``), run and sweep folders and their logs (``runs``), checkpoints, loggers, and a
finished run rebuilt from its folder (``restore``). It imports the data, envs, agents and
evaluation below it, never the report, generation or command-line modules above it
(``tests/test_imports.py`` holds the rules)."""
