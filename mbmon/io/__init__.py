"""mbmon.io"""
