"""mbmon.sim"""
