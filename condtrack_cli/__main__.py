from condtrack_cli.cli import main

main()
