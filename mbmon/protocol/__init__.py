"""mbmon.protocol"""
