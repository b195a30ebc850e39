"""This rig on an Eclipse Zenoh bus: poses, state, statistics, events, queries and liveliness."""
