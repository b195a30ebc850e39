"""Link backends behind one interface, chosen by name (see `base.Transport`)."""
