"""The contact model: candidate kinds, batched detection and Jacobians, effective mass, impulses.

Nothing here knows a particular system: a System declares its candidates with index tensors.
"""
