"""The coherent (complex-domain) reference cell search: a test and benchmark reference, not part of the pipeline."""
