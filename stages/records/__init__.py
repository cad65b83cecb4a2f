"""The files stages hand to each other: one module per output format, each a typed record with
`write(folder)` and `read(folder)`; the writing stage and every reader go through it."""
