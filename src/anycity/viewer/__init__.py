"""Look at a predicted scene: the viser viewer (``anycity view``) and fly-through videos (``anycity render-video``)."""
