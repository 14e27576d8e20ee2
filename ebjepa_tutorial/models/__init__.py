"""Networks: the image encoder and projector, the video JEPA, the world model."""
