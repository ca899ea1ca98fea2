"""Applications: what a user runs on images and models. ``predict`` (images in, assemblies,
poses and overlays out), the ``demo`` and its page, ``export`` of a trained model, and the
``fit`` of an assembly to the masks of views from known poses, with its figures. Each is a
function the CLI calls; they use the inference, training and evaluation layers below."""
