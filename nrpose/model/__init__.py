"""Data and their maths, no file I/O: rotations, skeletons, handles, characters, clips.

Readers and writers of these are :mod:`nrpose.io`.
"""
