"""Tabletop play as standard-message robot bags (bags.py): camera, joint states, commands, timed
annotations, with the ground truth beside them."""
