"""A mutation fuzzer for the ``nrpose`` command line.

``seeds`` makes small valid inputs of every kind the CLI reads, ``mutators`` breaks them
(bytes, tokens, JSON structure, headers, options, paths), ``cases`` assembles command lines
from them and ``runner`` runs each case in a forked child of a process that has imported
nrpose already, under a time and memory limit, and checks the contract: exit 0 with a
valid output, or exit 2 with one line on stderr and nothing left behind.
"""
