"""The teaching layer: presets (the scales), exercises and reference figures."""
