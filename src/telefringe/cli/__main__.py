import sys

from telefringe.cli import main

sys.exit(main())
