"""Training the disc classifier on the simulator, and adapting it to a site's images."""
