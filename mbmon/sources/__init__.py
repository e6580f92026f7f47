"""mbmon.sources"""
