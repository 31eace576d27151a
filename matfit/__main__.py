"""`python -m matfit` runs the command line."""

from matfit.cli import main

main()
