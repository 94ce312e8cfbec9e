"""Services: load rows, call the experiment core, write rows. They flush, never commit, and raise server.errors."""
