"""The `rangeret` command: `main` builds the parser, one module per command holds its options and
body. Nothing else in the project imports this package."""
