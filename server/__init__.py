"""trustlab web layer and command line; imports the experiment core, never the reverse."""
