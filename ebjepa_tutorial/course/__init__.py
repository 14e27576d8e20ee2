"""The teaching layer: the scales' presets, the exercises and the reference figures. Nothing
below this layer imports it."""
