"""nrpose's benchmarks, run from a checkout (``python -m bench``, ``make bench``); not
part of the installed package. The modules import each other by their plain names
(``import common``), with this folder on ``sys.path``, so each also runs as a script
(``python bench/table1.py ...``)."""
