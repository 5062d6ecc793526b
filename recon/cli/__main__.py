from recon.cli.main import main

main()
