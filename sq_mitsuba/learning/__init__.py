"""Learning layer: the network (EfficientNet-B0 encoder, superquadric and pose generators),
its losses, the training loop, and test-time fitting through the renderer. Imports the
geometry, render and data layers."""
