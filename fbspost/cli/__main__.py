"""``python -m fbspost.cli``."""
from . import main

main()
