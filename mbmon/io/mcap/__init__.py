"""mbmon's MCAP logs: :mod:`.layout` (topics, schemas, record -> messages), :mod:`.writer`
(chunks, compression, the writer thread) and :mod:`.reader` (the tolerant reader).

The reader imports neither of the others; nothing here imports the CLI or the sinks.
"""
