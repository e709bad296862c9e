"""python -m mmgp.cli: the command line without the console script."""
from . import main

main()
