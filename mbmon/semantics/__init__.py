"""mbmon.semantics"""
