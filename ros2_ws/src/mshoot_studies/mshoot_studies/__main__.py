"""``python -m mshoot_studies``: the ``mshoot`` command."""
from mshoot_studies.cli import console_main

if __name__ == '__main__':
    console_main()
