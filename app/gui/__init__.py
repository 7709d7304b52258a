"""The desktop application (PySide6, pyqtgraph). core/ and drivers/ never import from here."""

import pyqtgraph as pg

pg.setConfigOptions(imageAxisOrder="row-major", antialias=False)
