"""mbmon.sinks"""
