from clothgap.cli import main

main()
