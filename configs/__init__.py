"""The card's configuration files, shipped as this package's data: model presets (`models/`), rig files
(`rigs/`) and drive EDS files (`eds/`). Code reads them through `model.resources.card_folder`, never by a
path relative to the source tree, so an installed wheel finds them in its environment."""
