MODULE VisionCheck
  ! cellvision line protocol from an ABB controller (RAPID, RobotWare 6/7 with the socket
  ! messaging option). Triggers inspection number 1 and acts on its verdict and value.
  ! Server side (cell.yaml):   line: {enabled: true, host: 0.0.0.0, port: 7879}
  !   inspection 1 answers one value, e.g. presence: output: {fields: [value], decimals: 2}
  ! cellvision: format abb, numbers 2 (verdict, value)
  ! The answer to "T 1" in the abb format is "<verdict>,<value>" CR LF, at most 80 characters
  ! (a RAPID string): split at the comma, each field converted by StrToVal. A negative verdict
  ! is an error code (protocol/LINE.md section 6), e.g. -21: the deadline passed.
  ! Receive timeout 12 s: longer than the server's line deadline_s (10 s).

  VAR socketdev vision;
  VAR string answer;
  VAR string part;
  VAR num verdict;
  VAR num value;

  PROC vision_check()
    VAR num comma;
    VAR num cr;
    VAR bool ok;

    SocketCreate vision;
    SocketConnect vision, "192.168.0.10", 7879 \Time:=5;
    SocketSend vision \Str:="F abb\0A";
    ReceiveLine;
    SocketSend vision \Str:="T 1\0A";
    ReceiveLine;
    ! "1,100.00" CR LF: the verdict before the comma, the value up to the CR.
    comma := StrFind(answer, 1, ",");
    cr := StrFind(answer, 1, "\0D");
    ok := StrToVal(StrPart(answer, 1, comma - 1), verdict);
    IF ok ok := StrToVal(StrPart(answer, comma + 1, cr - comma - 1), value);
    SocketClose vision;
    IF NOT ok THEN
      ErrWrite "vision", "answer not understood: " + answer;
      Stop;
    ELSEIF verdict < 0 THEN
      ErrWrite "vision", "error code " + NumToStr(-verdict, 0);
    ELSEIF verdict = 1 THEN
      TPWrite "vision: pass, value " \Num:=value;
    ELSE
      TPWrite "vision: fail, value " \Num:=value;
    ENDIF
  ERROR
    IF ERRNO = ERR_SOCK_TIMEOUT THEN
      SocketClose vision;
      ErrWrite "vision", "no answer (timeout)";
      Stop;
    ENDIF
  ENDPROC

  ! One answer line: SocketReceive stores what has arrived; append until the LF.
  PROC ReceiveLine()
    answer := "";
    WHILE StrFind(answer, 1, "\0A") > StrLen(answer) DO
      SocketReceive vision \Str:=part \Time:=12;
      answer := answer + part;
    ENDWHILE
  ENDPROC
ENDMODULE
