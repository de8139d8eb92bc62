import sys

from northfinder.cli import main

sys.exit(main())
