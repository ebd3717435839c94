"""The runner: what stands around the protocol to make a run a record (the output folder's
record, its lock, staging and publishing)."""
