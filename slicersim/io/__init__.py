"""File I/O without physics: TOML configurations, ECSV/CSV curves, raw-ramp HDF5 files."""
