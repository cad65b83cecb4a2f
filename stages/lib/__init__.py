"""The libraries the stages share, one package per domain (pure functions, arrays in, arrays out): they import
libraries, records and the contract only, and know no Hydra, no cache and no stage."""
