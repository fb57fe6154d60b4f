"""References the tests and benchmarks check the pipeline against, not part of it: ``coherent``,
a coherent (complex-domain) cell search that gives the true cells and timing of a real I/Q
recording, which the envelope-domain search is then scored on."""
