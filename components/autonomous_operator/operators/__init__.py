"""The shipped autonomous operators, one script each, named in station data by file name
(``script = "steering"``). Each defines ``main(robot, ...)`` as any ``msctl run`` script;
its keyword parameters are what the data's ``params`` may give."""
