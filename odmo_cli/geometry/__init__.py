"""Geometry of a body: named skeletons, the LMP/trajectory split and bone lengths, and so(3)
kinematics. Pure typed functions on numpy arrays or torch tensors; nothing here knows datasets
or models."""
