"""The weak priors of NSD training.

Window position, scale and aspect, presence, proposals, depth.
"""
