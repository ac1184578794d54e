"""Mutation fuzzing of the readers: WOD records and files (`wod`, damaged by `wod_mutants`), Argoverse 2 feather logs
(`av2`), YAML configs (`config`) and sequences of users' own sweeps (`files`: point files, poses, timestamps, box
tables); the outcomes, report and watchdog they share (`report`). `tools/fuzz_reader.py` runs them with thousands of
mutants; `tests/fuzz/` with a few hundred."""
