"""One module per benchmark; each defines ``main(argv: list[str]) -> None`` and prints JSON lines via ``emit``."""
