from ilt.cli import main

main()
