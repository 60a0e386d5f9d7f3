"""The ATGS player (``atgs-view``, ``atgs-render``): installed as ``atgs.viewer`` from the folder
atgs/viewer/ (see docs/ARCHITECTURE.md); always import it as ``atgs.viewer``."""
