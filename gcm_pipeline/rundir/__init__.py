"""The run directory: its atomic transaction, the CSV and NPZ codecs, reading a run, exports."""
