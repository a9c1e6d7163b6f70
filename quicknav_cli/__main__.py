from quicknav_cli.main import main

main()
