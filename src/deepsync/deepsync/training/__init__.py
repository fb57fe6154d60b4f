"""Making the timing network: simulated training data (``dataset``) and the training loop (``train``).

Not a pipeline stage: it drives the simulator and the cell search's stacking to make examples,
and ``deepsync.timing`` (model, checkpoints, inference) is what the pipeline runs.
"""
