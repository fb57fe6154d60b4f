"""Cell search: frame stacking, PCI detection (single cells and co-sited pairs), windows for timing."""
