"""Independent references: plain NumPy/SciPy implementations written from the papers, one run or one
mixture at a time (the index, with which gmjax function each checks and how, is ``references/README.md``)."""
