from companion.cli import finish, main

finish(main())
