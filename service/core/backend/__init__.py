"""The back end: a pose graph over the front end's nodes, and the loop search that closes it."""
