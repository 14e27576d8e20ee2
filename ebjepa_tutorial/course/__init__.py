"""The teaching layer: the scales' presets, the exercises' checkers, student versions, the book.

Nothing below this layer imports it.
"""
