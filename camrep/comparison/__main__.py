"""`python -m camrep.comparison`: the comparison launcher (`camrep.comparison.command`)."""

import sys

from camrep.comparison import command

sys.exit(command.main())
