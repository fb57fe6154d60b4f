"""Cell search and classical timing: frame stacking, PCI detection, windows, fine estimators, CRLB."""
