"""Foundation.

Errors, the one source of defaults, atomic writes, the training loop, resumable stages,
data-parallel helpers.
"""
