"""HTTP routes: thin handlers that parse, call one service, return a schema."""
