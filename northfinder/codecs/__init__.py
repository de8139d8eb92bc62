"""Pure, byte-exact codecs for every device protocol in docs/PROTOCOLS.md. No I/O here."""
