import sys

from simvehicle.cli import main

sys.exit(main())
