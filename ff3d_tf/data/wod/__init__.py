"""Waymo Open Dataset v1: the graph decoder of Frame records, the segment reader and its diagnosis of bad records, format facts and the pair-records writer of segments."""
