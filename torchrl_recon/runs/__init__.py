"""What a run stands on, below the experiments that use it: run-directory files written
atomically and read back checked (``files``), published results packed and verified
(``archive``), what a result was made with (``provenance``), Ctrl-C that stops a run
(``interrupts``), malloc thresholds that keep freed memory (``allocator``) and round-robin
wall-clock timing (``timing``).

The data, training, trainer and report packages use these as the experiments do, so they live
beside ``experiments/`` rather than in it (reports read results without the experiments).
Importing this package imports none of them.
"""
